"""The input channel's listener for everything a page sends: keys, gamepads, the phone page, WebHID,
and whether its WebGL draws in software (handed to the app: teleop/web/shared/view_quality.py).

Messages arrive validated (`input_messages.parse`) on the network thread and go
straight into the devices' own locked mailboxes (`devices/gamepad.py`,
`devices/phone.py`, `devices/webhid.py`); the control loop polls those like any
device. Whatever a page was holding is let go when its channel closes or stops
answering pings: a pad's sticks, the phone's clutch, a SpaceMouse's deflection.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path

from devices.gamepad import GamepadDevice
from devices.phone import PhoneDevice
from devices.webhid import BrowserHidHandle, WebHidSpaceMouse
from teleop.web.shared.input_messages import (
    Gamepad, Hid, HidConnect, HidDisconnect, InputMessage, Phone, PhoneButton, View,
)
from teleop.web.session_page.page_keyboard import PageKeys
from teleop.web.viser_internals.page_script import GUI_BUTTON_SELECTOR

SCRIPT = Path(__file__).with_name("page_devices.js")
PHONE_PAGE = Path(__file__).with_name("phone.html")
CONNECT_SPACEMOUSE = "Connect SpaceMouse"  # the panel button whose click asks the browser for a WebHID device


class PageInputs:
    """Hands each page's messages to the device they are for (the first of each kind given)."""

    def __init__(self, keys: PageKeys | None, devices: list) -> None:
        self.keys = keys
        self.gamepad: GamepadDevice | None = next((d for d in devices if isinstance(d, GamepadDevice)), None)
        self.phone: PhoneDevice | None = next((d for d in devices if isinstance(d, PhoneDevice)), None)
        self.webhid: WebHidSpaceMouse | None = next((d for d in devices if isinstance(d, WebHidSpaceMouse)), None)
        self._owner: dict[str, int] = {}  # "gamepad" / "phone" -> the connection that sent the newest state
        self._hid: dict[int, BrowserHidHandle] = {}  # connection -> its WebHID device's reports
        self._lock = threading.Lock()
        self.unused = 0  # valid messages for a device this session does not run
        self.on_view: Callable[[int, bool], None] | None = None  # (viser client id, software WebGL)

    @property
    def any_device(self) -> bool:
        return any(d is not None for d in (self.gamepad, self.phone, self.webhid))

    def script(self) -> str:
        """The page's gamepad / WebHID script, run with the input channel's sender."""
        source = SCRIPT.read_text(encoding="utf-8").strip().rstrip(";")
        # The panel's button, as viser draws it (viser_internals.page_script): found by the page from its selector and label.
        ui = json.dumps({"button": GUI_BUTTON_SELECTOR, "connectSpaceMouse": CONNECT_SPACEMOUSE})
        send = "(m) => window.__teleopInput && window.__teleopInput.sendRaw(JSON.stringify(m))"
        return f"\n{source}({send}, {ui});\n"

    @staticmethod
    def phone_page() -> bytes:
        return PHONE_PAGE.read_bytes()

    # -- InputListener (network thread) -------------------------------------
    def opened(self, conn: int, remote: str) -> None:
        if self.keys is not None:
            self.keys.opened(conn, remote)

    def received(self, conn: int, message: InputMessage) -> None:
        if isinstance(message, View):
            if self.on_view is not None and message.client is not None:
                self.on_view(message.client, message.software_gl)
        elif isinstance(message, Gamepad):
            self._gamepad(conn, message)
        elif isinstance(message, Phone):
            self._with("phone", conn, lambda p: p.push_pose(message.quat, message.pos, message.clutch))
        elif isinstance(message, PhoneButton):
            self._with("phone", conn, lambda p: p.press(message.action))
        elif isinstance(message, (Hid, HidConnect, HidDisconnect)):
            self._hid_message(conn, message)
        elif self.keys is not None:
            self.keys.received(conn, message)
        else:
            self.unused += 1

    def quiet(self, conn: int) -> None:
        self._let_go(conn)
        if self.keys is not None:
            self.keys.quiet(conn)

    def closed(self, conn: int) -> None:
        self._let_go(conn)
        if self.keys is not None:
            self.keys.closed(conn)

    # -- the devices -----------------------------------------------------------
    def _gamepad(self, conn: int, message: Gamepad) -> None:
        pad = self.gamepad
        if pad is None:
            self.unused += 1
            return
        with self._lock:
            self._owner["gamepad"] = conn
        if message.connected:
            pad.push(message.axes, message.buttons, message.pad_id)
        else:
            pad.release()

    def _with(self, kind: str, conn: int, act) -> None:
        device = self.phone
        if device is None:
            self.unused += 1
            return
        with self._lock:
            self._owner[kind] = conn
        act(device)

    def _hid_message(self, conn: int, message) -> None:
        device = self.webhid
        if device is None:
            self.unused += 1
            return
        if isinstance(message, HidConnect):
            handle = device.source.connect(message.product)
            with self._lock:
                self._hid[conn] = handle
            return
        with self._lock:
            handle = self._hid.get(conn) if isinstance(message, Hid) else self._hid.pop(conn, None)
        if isinstance(message, HidDisconnect):
            device.source.disconnect(handle) if handle is not None else None
        elif handle is not None:
            handle.push(message.report_id, message.data)
        else:
            self.unused += 1  # reports before hid_connect

    def _let_go(self, conn: int) -> None:
        """This page went quiet or away: release what it held."""
        with self._lock:
            owned = [kind for kind, owner in self._owner.items() if owner == conn]
            for kind in owned:
                del self._owner[kind]
            handle = self._hid.pop(conn, None)
        if "gamepad" in owned and self.gamepad is not None:
            self.gamepad.release()
        if "phone" in owned and self.phone is not None:
            self.phone.release()
        if handle is not None and self.webhid is not None:
            self.webhid.source.disconnect(handle)
