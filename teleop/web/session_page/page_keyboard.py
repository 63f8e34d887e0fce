"""Keys typed in the teleop page drive the arm, with the server keyboard's bindings and speeds.

The page sends key presses and releases over the input channel (page_input.js,
input_channel); `PageKeys` feeds them into a keyboard device's `KeyState`,
one source per browser, so `KeyboardDevice.poll` (hold-to-move at
`--pos-speed`/`--rot-speed`, one-shot keys, tab, c, +/-) is the one place
keys become Commands. The state fed is that of this machine's keyboard
device when one runs (a browser on the same desktop is then seen twice, by
pynput and by the page, and a shared state moves once), else a
`PageKeyboardDevice`, the same device with no pynput behind it.

No runaway arm: a browser's keys are all released when its page loses focus
or is hidden (the page says so), when its connection closes or stops
answering pings (input_channel.QUIET_S), and when viser's connection of that
page closes.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass

from devices.keyboard import KeyboardDevice
from teleop.web.shared.input_channel import channel_script
from teleop.web.shared.input_messages import Hello, InputMessage, Key, ReleaseAll, browser_keys


class PageKeyboardDevice(KeyboardDevice):
    """The keyboard device fed only by browser pages (no pynput, so no display needed)."""

    kind = "keyboard"

    def __init__(self, pos_speed: float = 0.15, rot_speed: float = 0.8, n_arms: int = 1,
                 name: str = "page keyboard") -> None:
        super().__init__(pos_speed=pos_speed, rot_speed=rot_speed, n_arms=n_arms, name=name)
        self.describe = lambda: "no browser"  # set by PageKeys: who drives

    def start(self) -> None:
        self._closed = False

    @property
    def last_input_time(self) -> float:
        """When a key last went down in a page (devices.base.InputStamped): the page's input-to-drawn latency
        and the campaign bench's key latency start there."""
        return self.keys.last_press_time

    def status(self) -> str:
        return "closed" if self._closed else self.describe()

    def close(self) -> None:
        self._closed = True
        self.keys.clear()


@dataclass
class _Browser:
    remote: str
    client: int | None = None  # viser's client id of the page, once it said hello
    agent: str = ""

    def label(self, conn: int) -> str:
        who = f"browser {self.client}" if self.client is not None else f"page {conn}"
        product = _product(self.agent)
        return f"{who} ({', '.join(x for x in (self.remote, product) if x)})"


def _product(agent: str) -> str:
    """'Firefox 133' / 'Chrome 131' / ... from a user agent string, '' when unknown."""
    for name, pattern in (("Firefox", r"Firefox/(\d+)"), ("Edge", r"Edg/(\d+)"), ("Chrome", r"Chrome/(\d+)"),
                          ("Safari", r"Version/(\d+).*Safari/")):
        match = re.search(pattern, agent)
        if match:
            return f"{name} {match.group(1)}"
    return ""


def _source(conn: int) -> str:
    return f"page:{conn}"


class PageKeys:
    """The input channel's listener: browsers' keys into `keyboard.keys`, one source per connection."""

    def __init__(self, keyboard: KeyboardDevice) -> None:
        self.keyboard = keyboard
        self._browsers: dict[int, _Browser] = {}
        self._lock = threading.Lock()
        self.releases = 0  # times a browser's held keys were let go for it (blur, hidden, quiet, gone)
        self.last_release = ""  # why, the last time: the page's reason, "quiet", "closed" or "viser closed"
        if isinstance(keyboard, PageKeyboardDevice):
            keyboard.describe = self.describe

    # -- InputListener (called on the network thread) ----------------------
    def opened(self, conn: int, remote: str) -> None:
        with self._lock:
            self._browsers[conn] = _Browser(remote=remote)

    def received(self, conn: int, message: InputMessage) -> None:
        now = time.monotonic()
        with self._lock:
            browser = self._browsers.get(conn)
            if browser is None:
                return
            if isinstance(message, Hello):
                browser.client, browser.agent = message.client, message.agent
        keys = self.keyboard.keys
        if isinstance(message, Key):
            if message.down:
                keys.press(message.name, now, _source(conn))
            else:
                keys.release(message.name, now, _source(conn))
        elif isinstance(message, ReleaseAll):
            self._release(conn, now, message.why)

    def quiet(self, conn: int) -> None:
        self._release(conn, time.monotonic(), "quiet")

    def closed(self, conn: int) -> None:
        self._release(conn, time.monotonic(), "closed")
        with self._lock:
            self._browsers.pop(conn, None)

    # -- from the web app ----------------------------------------------------
    def release_client(self, client: int) -> None:
        """viser's connection of page `client` closed: let go of that page's keys too."""
        with self._lock:
            conns = [c for c, b in self._browsers.items() if b.client == client]
        for conn in conns:
            self._release(conn, time.monotonic(), "viser closed")

    def release_all(self) -> None:
        with self._lock:
            conns = list(self._browsers)
        for conn in conns:
            self._release(conn, time.monotonic(), "stopping")

    def _release(self, conn: int, now: float, why: str) -> None:
        if self.keyboard.keys.release_source(_source(conn), now):
            self.releases += 1
            self.last_release = why

    def script(self, client: int) -> str:
        """The page's script (page_input.js) for viser's client `client`, its settings prepended."""
        return channel_script(client, browser_keys())

    # -- what the panel and the status say ------------------------------------
    def state(self) -> dict:
        """browsers connected, the one driving (the newest press) and the keys each holds."""
        holding = self.keyboard.keys.holding()
        with self._lock:
            labels = {conn: b.label(conn) for conn, b in self._browsers.items()}
        held = {labels[conn]: holding.get(_source(conn), []) for conn in labels}
        last = self.keyboard.keys.last_source
        driving = None
        if last is not None and last.startswith("page:"):
            driving = labels.get(int(last.partition(":")[2]))
        elif last is not None:
            driving = "this machine's keyboard"
        return {"browsers": len(labels), "driving": driving, "held": {k: v for k, v in held.items() if v},
                "releases": self.releases, "last_release": self.last_release or None}

    def describe(self) -> str:
        """One line for the panel's Devices section: how many browsers, which one drives, its keys."""
        state = self.state()
        count = state["browsers"]
        if not count:
            return "keys in the page: no browser"
        head = f"keys in the page: {count} browser{'s' if count != 1 else ''}"
        driving = state["driving"]
        if driving is None:
            return head + " (click the 3D view, then hold w/a/s/d/r/f...)"
        keys = state["held"].get(driving)
        return head + f" · driving: {driving}" + (f", holding {' '.join(keys)}" if keys else "")
