"""A SpaceMouse plugged into the operator's machine, read by the browser's WebHID and sent here.

WebHID hands the page each input report as (reportId, data without the id).
`BrowserHidHandle` puts the id back in front and queues the bytes, and
`SpaceMouseDevice` reads them through the same `read()` its hidraw handle
offers, so the browser's reports go through the same parser, deadzone and
axis mapping (`devices/spacemouse_protocol.py`) as a local device's.

When the browser goes away the handle reads as unplugged (the device stops
all motion at once) and the device waits for the next browser to connect one.
"""

from __future__ import annotations

import collections
import threading

from devices.base import DeviceError
from devices.spacemouse import SpaceMouseDevice

MAX_REPORT_BYTES = 64  # SpaceMouse reports are 7 or 13 bytes with the id; anything longer is not one
RECONNECT_CHECK_S = 2.0  # s: the reader waiting for a browser's device looks again this often even unwoken
MAX_QUEUED = 256  # ~2-4 s of reports; older ones are dropped first if the loop cannot keep up


class BrowserHidHandle:
    """Reports from one browser's WebHID device, read like a hidraw handle (`devices.spacemouse.HidHandle`)."""

    def __init__(self) -> None:
        self._queue: collections.deque[bytes] = collections.deque(maxlen=MAX_QUEUED)
        self._ready = threading.Condition()
        self._closed = False
        self.product = ""  # what the browser says the device is ("SpaceMouse Compact")

    def push(self, report_id: int, data: bytes) -> bool:
        """Queue one report; False (dropped) if it cannot be a SpaceMouse report or the handle is closed."""
        if not 0 <= report_id <= 255 or len(data) + 1 > MAX_REPORT_BYTES or self._closed:
            return False
        with self._ready:
            self._queue.append(bytes([report_id]) + bytes(data))
            self._ready.notify()
        return True

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        """The next report (id first), [] after `timeout_ms` without one; OSError once closed (unplugged)."""
        with self._ready:
            if not self._queue and not self._closed and timeout_ms > 0:
                self._ready.wait(timeout_ms / 1000.0)
            if self._queue:
                return list(self._queue.popleft()[:max_length])
            if self._closed:
                raise OSError("the browser's SpaceMouse went away")
            return []

    def close(self) -> None:
        with self._ready:
            self._closed = True
            self._ready.notify_all()


class BrowserSpaceMouse:
    """The opener a SpaceMouseDevice reconnects through: the newest browser handle, if any."""

    def __init__(self) -> None:
        self.handle: BrowserHidHandle | None = None
        self._lock = threading.Lock()
        self.arrived = threading.Event()  # set by connect(): the reader need not poll for a browser's device

    def connect(self, product: str = "") -> BrowserHidHandle:
        """A browser granted a device: new reports go to a new handle (the old one reads as unplugged)."""
        handle = BrowserHidHandle()
        handle.product = product[:80]
        with self._lock:
            old, self.handle = self.handle, handle
        if old is not None:
            old.close()
        self.arrived.set()
        return handle

    def disconnect(self, handle: BrowserHidHandle | None = None) -> None:
        """That browser (or, with None, whichever) stopped sending: stop all motion."""
        with self._lock:
            if handle is not None and handle is not self.handle:
                return
            old, self.handle = self.handle, None
        if old is not None:
            old.close()

    def __call__(self) -> BrowserHidHandle:
        with self._lock:
            handle = self.handle
        if handle is None or handle._closed:
            raise DeviceError("no SpaceMouse connected in a browser (click 'Connect SpaceMouse' in the panel)")
        return handle


class WebHidSpaceMouse(SpaceMouseDevice):
    """A SpaceMouseDevice fed by browsers (`source.connect()` / `push`), waiting for one at start.

    options: as SpaceMouseDevice (arm, pos_speed, rot_speed, stance, deadzone, ...).
    """

    kind = "webhid"

    def __init__(self, name: str = "webhid-spacemouse", **options) -> None:
        self.source = BrowserSpaceMouse()
        super().__init__(self.source, name=name, **options)

    def close(self) -> None:
        self._stop.set()
        self.source.arrived.set()  # wakes the reader waiting for a browser's device
        super().close()

    def _wait_to_reconnect(self) -> None:
        """Until a browser connects a device (or close()), not polling: most sessions never get one."""
        self.source.arrived.wait(RECONNECT_CHECK_S)
        self.source.arrived.clear()

    def start(self) -> None:
        """Read in the background; a device arrives when a browser connects one (no error without one)."""
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()

    def status(self) -> str:
        if self._stop.is_set():
            return "closed"
        handle = self.source.handle
        if self._connected and handle is not None:
            return f"{handle.product or 'SpaceMouse'} in a browser"
        return "waiting for a browser to connect one (WebHID, Chromium)"
