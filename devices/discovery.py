"""Which input devices this machine offers, and for each one that it does not, why.

Answers the field's top two complaints (keys that never arrive, SpaceMice that
fail to open) before a session starts: `teleop devices` prints this list.
"""

from __future__ import annotations

import glob
import os
import sys
from dataclasses import dataclass, field

from devices.base import DeviceError


@dataclass
class DeviceInfo:
    """One row of `teleop devices`: name is what `--device` takes."""

    name: str
    kind: str
    available: bool
    reason: str
    extra: dict = field(default_factory=dict)

    def to_dict(self) -> dict:
        return {"name": self.name, "kind": self.kind, "available": self.available, "reason": self.reason, **self.extra}


def keyboard_info() -> DeviceInfo:
    """Can pynput read keys here? Imports pynput (which connects to the display) to find out."""
    from devices.keyboard import import_pynput_keyboard, wayland_note

    try:
        keyboard = import_pynput_keyboard()
    except DeviceError as exc:
        return DeviceInfo("keyboard", "keyboard", False, str(exc))
    if sys.platform == "darwin":
        listener = keyboard.Listener()
        listener.start()
        listener.wait()
        trusted = getattr(listener, "IS_TRUSTED", True)
        listener.stop()
        if trusted is False:
            return DeviceInfo(
                "keyboard", "keyboard", False,
                "macOS does not let this app read the keyboard: System Settings > Privacy & Security > "
                "Accessibility and Input Monitoring: allow your terminal, then restart it",
            )
        return DeviceInfo("keyboard", "keyboard", True, "reads keys typed into any window")
    where = f"X display {os.environ['DISPLAY']}" if os.environ.get("DISPLAY") else "this desktop"
    reason = f"reads keys typed into any window of {where}"
    note = wayland_note() if sys.platform.startswith("linux") else ""
    return DeviceInfo("keyboard", "keyboard", True, f"{reason}; {note}" if note else reason)


def _no_spacemouse_reason() -> str:
    base = "no SpaceMouse found (no 3Dconnexion 6-DoF device on USB or a receiver)"
    if sys.platform.startswith("linux"):
        nodes = glob.glob("/dev/hidraw*")
        if not nodes:
            return base + "; this machine has no /dev/hidraw* nodes at all (in a container, pass the device in)"
    return base


def spacemouse_infos() -> list[DeviceInfo]:
    """One row per SpaceMouse (opened briefly to prove it can be), or one row saying why there is none."""
    from devices.spacemouse import find_spacemice, open_hid, spacenavd_running

    try:
        found = find_spacemice()
    except DeviceError as exc:
        return [DeviceInfo("spacemouse", "spacemouse", False, str(exc))]
    if not found:
        return [DeviceInfo("spacemouse", "spacemouse", False, _no_spacemouse_reason())]
    rows = []
    daemon = spacenavd_running()
    for i, info in enumerate(found):
        path = info.get("path") or b""
        extra = {
            "model": info["model"],
            "vendor_id": f"{info['vendor_id']:04x}",
            "product_id": f"{info['product_id']:04x}",
            "path": path.decode(errors="replace") if isinstance(path, bytes) else str(path),
            "serial": info.get("serial_number") or "",
        }
        try:
            open_hid(info).close()
        except DeviceError as exc:
            rows.append(DeviceInfo(f"spacemouse:{i}", "spacemouse", False, str(exc), extra))
            continue
        reason = f"{info['model']} at {extra['path']}"
        if daemon:
            reason += "; spacenavd is running too and also reacts to it (`sudo systemctl stop spacenavd`)"
        rows.append(DeviceInfo(f"spacemouse:{i}", "spacemouse", True, reason, extra))
    return rows


def discover() -> list[DeviceInfo]:
    """Every input device kind, in the order `teleop devices` lists them."""
    return [
        keyboard_info(),
        *spacemouse_infos(),
        DeviceInfo("gizmo", "gizmo", True, "drag the target in the browser (teleop serve, or --device gizmo)"),
        DeviceInfo("script", "script", True, "replays commands from a JSON file: --device script:FILE.json"),
        DeviceInfo("gamepad", "gamepad", True, "a pad plugged into the browser's machine (Gamepad API; teleop serve)"),
        DeviceInfo("phone", "phone", True, "a phone's browser on the page's /phone address (WebXR or device "
                   "orientation; needs https or an SSH tunnel; teleop serve)"),
        DeviceInfo("webhid", "webhid", True, "a SpaceMouse plugged into the browser's machine, connected from the "
                   "panel (WebHID, Chromium; teleop serve)"),
    ]
