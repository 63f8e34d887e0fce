"""SpaceMouse device: a thread reads HID reports, `poll` turns the held state into Commands.

The thread exists because a SpaceMouse sends 60-125 reports/s whatever the
control rate: reading them as they come keeps the latest deflection ready for
the next tick (no queue to drain, no lag beyond one tick). The HID handle is
anything with `read(max_len, timeout_ms) -> list[int]` and `close()`, opened by
an `opener` callable, so an unplugged device can be reopened later (and a
stand-in handle can feed recorded bytes through the same thread).
"""

from __future__ import annotations

import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Protocol

import numpy as np

from devices.base import DeviceError
from devices.spacemouse_protocol import RawState, apply_report, is_spacemouse, model_name, normalize, to_world
from devices.command import EVENTS, Command
from devices.view import SessionView

UDEV_RULES = (
    'KERNEL=="hidraw*", ATTRS{idVendor}=="256f", MODE="0666"\n'
    'KERNEL=="hidraw*", ATTRS{idVendor}=="046d", ATTRS{idProduct}=="c6[0-2]?", MODE="0666"\n'
)
UDEV_FILE = "/etc/udev/rules.d/99-spacemouse.rules"
UDEV_HOWTO = (
    f"sudo tee {UDEV_FILE} <<'EOF'\n{UDEV_RULES}EOF\n"
    "sudo udevadm control --reload-rules && sudo udevadm trigger   # then replug the SpaceMouse"
)
RIGHT_BUTTON_ACTIONS = ("none", "gripper", "frame", *EVENTS)
GRIPPER_MODES = ("toggle", "hold")
READ_TIMEOUT_MS = 50  # bounds how long close() waits for the thread


class HidHandle(Protocol):
    """The two calls the reading thread needs from an open HID device."""

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]: ...

    def close(self) -> None: ...


Opener = Callable[[], HidHandle]


def hid_backend():
    """The hidapi module to use: `hidraw` on Linux (no libusb detach), else `hid`.

    Raises DeviceError when hidapi is not installed.
    """
    try:
        if sys.platform.startswith("linux"):
            try:
                import hidraw

                return hidraw
            except ImportError:
                pass
        import hid

        return hid
    except ImportError:
        raise DeviceError("the hidapi package is missing: pip install hidapi") from None


def find_spacemice() -> list[dict]:
    """Every SpaceMouse the HID backend can see, in a stable order (by path).

    Each entry is hidapi's enumerate() dict plus "model". Seeing a device does
    not mean it can be opened (see `open_problem`).
    """
    backend = hid_backend()
    found = []
    seen: set[bytes] = set()
    for info in backend.enumerate():
        path = info.get("path") or b""
        if path in seen:
            continue
        if not is_spacemouse(info.get("vendor_id", 0), info.get("product_id", 0), info.get("usage_page", 0), info.get("usage", 0)):
            continue
        seen.add(path)
        found.append({**info, "model": model_name(info["vendor_id"], info["product_id"])})
    found.sort(key=lambda i: i.get("path") or b"")
    return found


def spacenavd_running() -> bool:
    """True when a spacenavd daemon runs here (it may hold the device or see the same motions)."""
    try:
        pids = [p for p in os.listdir("/proc") if p.isdigit()]
    except OSError:
        return False
    for pid in pids:
        try:
            with open(f"/proc/{pid}/comm") as f:
                if f.read().strip() == "spacenavd":
                    return True
        except OSError:
            continue
    return False


def _path_str(info: dict) -> str:
    path = info.get("path") or b""
    return path.decode(errors="replace") if isinstance(path, bytes) else str(path)


def open_problem(info: dict) -> str | None:
    """Why this process cannot open the device, checked without opening it (Linux hidraw)."""
    path = _path_str(info)
    if path.startswith("/dev/") and not os.path.exists(path):
        return f"{path} ({info.get('model', 'SpaceMouse')}) is gone: unplugged?"
    if path.startswith("/dev/") and not os.access(path, os.R_OK | os.W_OK):
        return (
            f"permission denied on {path} ({info.get('model', 'SpaceMouse')}): add the udev rule "
            f"'{UDEV_RULES.splitlines()[0]}' to {UDEV_FILE}, run `sudo udevadm control --reload-rules "
            "&& sudo udevadm trigger` and replug (`teleop devices` prints the full rule)"
        )
    return None


def open_hid(info: dict) -> HidHandle:
    """Open one enumerated device; DeviceError says why not and how to fix it."""
    problem = open_problem(info)
    if problem:
        raise DeviceError(problem)
    handle = hid_backend().device()
    try:
        handle.open_path(info["path"])
    except (OSError, ValueError) as exc:
        where = f"{_path_str(info)} ({info.get('model', 'SpaceMouse')})"
        if spacenavd_running():
            raise DeviceError(
                f"cannot open {where}: spacenavd is holding it; stop it with `sudo systemctl stop spacenavd`"
            ) from None
        raise DeviceError(f"cannot open {where}: {exc} (another program such as 3DxWare may hold it)") from None
    return handle


def reopener(info: dict, index: int) -> Opener:
    """An opener that finds the same device again after a replug (its path may change).

    Matches by serial number when the device has one, else by model and
    position among the connected SpaceMice.
    """
    serial = info.get("serial_number") or ""
    key = (info.get("vendor_id"), info.get("product_id"))

    def open_again() -> HidHandle:
        found = find_spacemice()
        same = [i for i in found if (i.get("vendor_id"), i.get("product_id")) == key]
        if serial:
            same = [i for i in same if i.get("serial_number") == serial]
        if not same:
            raise DeviceError(f"{info.get('model', 'SpaceMouse')} is not connected")
        return open_hid(same[min(index, len(same) - 1)] if not serial else same[0])

    return open_again


class SpaceMouseDevice:
    """One SpaceMouse driving one arm; deltas at `pos_speed`/`rot_speed` at full deflection.

    stance: "behind" or "facing" (see spacemouse_protocol.STANCES).
    gripper_mode: "toggle" (left press toggles) or "hold" (closed while held).
    right_button: one of RIGHT_BUTTON_ACTIONS.
    deadzone: fraction of full scale read as zero; sensitivity multiplies both speeds.
    """

    kind = "spacemouse"

    def __init__(
        self,
        opener: Opener,
        *,
        name: str = "spacemouse",
        arm: int = 0,
        pos_speed: float = 0.15,
        rot_speed: float = 0.8,
        stance: str = "behind",
        deadzone: float = 0.03,
        sensitivity: float = 1.0,
        gripper_mode: str = "toggle",
        right_button: str = "reset",
        reconnect_interval: float = 0.5,
    ) -> None:
        if stance not in ("behind", "facing"):
            raise DeviceError(f"unknown SpaceMouse stance {stance!r} (use behind or facing)")
        if gripper_mode not in GRIPPER_MODES:
            raise DeviceError(f"unknown gripper mode {gripper_mode!r} (use toggle or hold)")
        if right_button not in RIGHT_BUTTON_ACTIONS:
            raise DeviceError(f"unknown right-button action {right_button!r} (use one of {', '.join(RIGHT_BUTTON_ACTIONS)})")
        self.name = name
        self.arm = arm
        self.pos_speed = pos_speed
        self.rot_speed = rot_speed
        self.stance = stance
        self.deadzone = deadzone
        self.sensitivity = sensitivity
        self.gripper_mode = gripper_mode
        self.right_button = right_button
        self.frame = "world"
        self.reconnect_interval = reconnect_interval
        self.problem = ""  # last open/read error, for the panel
        self.reports = 0  # reports parsed since start, for diagnostics
        self.last_report_time = 0.0  # time.monotonic() of the last parsed report
        self._opener = opener
        self._handle: HidHandle | None = None
        self._raw = RawState()
        self._pending: list[tuple[str, str]] = []  # button edges since the last poll, in order
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False

    # -- life cycle -------------------------------------------------------
    def start(self) -> None:
        """Open the device now (so a wrong setup fails loudly), then read in the background."""
        self._handle = self._opener()
        self._connected = True
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self._drop_handle()

    @property
    def finished(self) -> bool:
        return False

    def status(self) -> str:
        if self._stop.is_set():
            return "closed"
        return "connected" if self._connected else "disconnected"

    # -- reading thread ---------------------------------------------------
    def _run(self) -> None:
        while not self._stop.is_set():
            if self._handle is None and not self._reconnect():
                self._wait_to_reconnect()
                continue
            try:
                data = self._handle.read(64, READ_TIMEOUT_MS)
            except (OSError, ValueError) as exc:  # unplugged: hidapi raises OSError("read error")
                self._disconnected(f"read failed: {exc}")
                continue
            if data:
                self._take(data)

    def _wait_to_reconnect(self) -> None:
        """Between tries to open the device (a device plugged in is found by trying)."""
        self._stop.wait(self.reconnect_interval)

    def _reconnect(self) -> bool:
        try:
            handle = self._opener()
        except DeviceError as exc:
            self.problem = str(exc)
            return False
        with self._lock:
            self._handle = handle
            self._connected = True
            self.problem = ""
        return True

    def _disconnected(self, why: str) -> None:
        """Stop all motion (holding the last deflection would run the arm away) and release buttons."""
        self._drop_handle()
        with self._lock:
            self._connected = False
            self.problem = why
            self._raw.axes[:] = [0] * 6
            if self.gripper_mode == "hold" and self._raw.buttons & 1:
                self._pending.append(("left", "up"))
            self._raw.buttons = 0

    def _drop_handle(self) -> None:
        handle, self._handle = self._handle, None
        if handle is not None:
            try:
                handle.close()
            except (OSError, ValueError):
                pass

    def _take(self, data: list[int] | bytes) -> None:
        now = time.monotonic()
        with self._lock:
            before = self._raw.buttons
            if apply_report(self._raw, data) is None:
                return
            self.reports += 1
            self.last_report_time = now
            changed = before ^ self._raw.buttons
            for bit, button in ((1, "left"), (2, "right")):
                if changed & bit:
                    self._pending.append((button, "down" if self._raw.buttons & bit else "up"))

    # -- control tick -----------------------------------------------------
    def poll(self, view: SessionView, dt: float) -> list[Command]:
        """Deltas for this tick from the latest deflection, plus any button actions since the last tick."""
        with self._lock:
            raw = list(self._raw.axes)
            edges, self._pending = self._pending, []
        if not edges and not any(raw):
            return []  # at rest (most ticks): nothing to send, and no arithmetic to do
        axes = normalize(raw, self.deadzone)
        trans, rot = to_world(axes, self.stance)
        scale = self.sensitivity * dt
        commands: list[Command] = []
        for button, edge in edges:
            self._button(button, edge, commands)
        motion = Command(
            translation=trans * self.pos_speed * scale,
            rotation=rot * self.rot_speed * scale,
            frame=self.frame,
            arm=self.arm,
            source=self.name,
        )
        if commands:
            first = commands[0]
            motion.gripper, motion.events = first.gripper, first.events
            commands[0] = motion
        elif not motion.is_idle():
            commands.append(motion)
        return commands

    def _button(self, button: str, edge: str, out: list[Command]) -> None:
        action = "gripper" if button == "left" else self.right_button
        if action == "gripper":
            if self.gripper_mode == "hold":
                out.append(Command(gripper="close" if edge == "down" else "open", arm=self.arm, source=self.name))
            elif edge == "down":
                out.append(Command(gripper="toggle", arm=self.arm, source=self.name))
        elif edge != "down" or action == "none":
            return
        elif action == "frame":
            self.frame = "ee" if self.frame == "world" else "world"
        else:
            out.append(Command(events=(action,), arm=self.arm, source=self.name))

    def axes(self) -> np.ndarray:
        """Current normalized deflection (6,), HID axis order: for panels and diagnostics."""
        with self._lock:
            return normalize(list(self._raw.axes), self.deadzone)
