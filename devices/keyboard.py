"""Keyboard device: hold a key to move the target at a set speed, release to stop.

pynput's listener thread records when each bound key goes down and up; each
control tick `poll` turns the time every key was held since the previous tick
into a delta (speed x dt x held fraction), so motion does not depend on key
autorepeat, a tap shorter than a tick still moves a little, and release stops
at once. pynput is imported only in `start`, because importing it without a
display raises (and we want one clear line instead).

pynput listens to the whole X display, not one window: keys typed into any X
window move the robot while the session runs.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from devices.base import DeviceError
from devices.command import Command
from devices.view import SessionView

SPEED_STEP = 1.5  # factor per speed-up / speed-down press
SPEED_LIMITS = (0.1, 10.0)
REPEAT_GAP = 0.03  # s: a press this soon after a release of the same key is autorepeat, not a new press
READY_TIMEOUT = 3.0  # s to wait for pynput's listener to come up


@dataclass(frozen=True)
class Binding:
    """One row of the key table: the keys (pynput names), what they do, and the help text."""

    keys: tuple[str, ...]
    action: str
    help: str


BINDINGS: tuple[Binding, ...] = (
    Binding(("w",), "+x", "move +x (away from the robot's base), hold"),
    Binding(("s",), "-x", "move -x (toward the base), hold"),
    Binding(("a",), "+y", "move +y (robot's left), hold"),
    Binding(("d",), "-y", "move -y (robot's right), hold"),
    Binding(("r",), "+z", "move up, hold"),
    Binding(("f",), "-z", "move down, hold"),
    Binding(("u",), "+roll", "rotate + about x (roll), hold"),
    Binding(("o",), "-roll", "rotate - about x (roll), hold"),
    Binding(("i",), "+pitch", "rotate + about y (pitch), hold"),
    Binding(("k",), "-pitch", "rotate - about y (pitch), hold"),
    Binding(("j",), "+yaw", "rotate + about z (yaw left), hold"),
    Binding(("l",), "-yaw", "rotate - about z (yaw right), hold"),
    Binding(("space",), "gripper", "toggle the gripper"),
    Binding(("b",), "start", "start (begin) recording an episode"),
    Binding(("enter",), "save", "save the episode"),
    Binding(("backspace",), "discard", "discard the episode"),
    Binding(("n",), "reset", "reset the scene (new seed)"),
    Binding(("p",), "policy", "hand control back to the policy (teleop serve --policy)"),
    Binding(("tab",), "arm", "switch arm (bimanual)"),
    Binding(("c",), "frame", "switch frame: world / end effector"),
    Binding(("=", "+"), "faster", f"speed up (x{SPEED_STEP})"),
    Binding(("-",), "slower", f"speed down (/{SPEED_STEP})"),
)

# action -> (which delta, axis, sign) for the hold-to-move keys
MOTION: dict[str, tuple[str, int, float]] = {
    f"{sign}{axis}": (delta, i, 1.0 if sign == "+" else -1.0)
    for delta, axes in (("translation", ("x", "y", "z")), ("rotation", ("roll", "pitch", "yaw")))
    for i, axis in enumerate(axes)
    for sign in "+-"
}
KEY_ACTION: dict[str, str] = {key: b.action for b in BINDINGS for key in b.keys}
ALIASES = {"+": "=", "_": "-"}  # shift changes the char between press and release
# While one of these is down, bound keys are ignored: the combination is meant for another app.
MODIFIERS = frozenset({"ctrl", "ctrl_l", "ctrl_r", "alt", "alt_l", "alt_r", "alt_gr", "cmd", "cmd_l", "cmd_r"})


def bindings_table() -> str:
    """The key table as aligned text (for `teleop devices` and docs/session.md)."""
    rows = [(" / ".join(b.keys), b.help) for b in BINDINGS]
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"  {k.ljust(width)}  {h}" for k, h in rows)


LOCAL = "local"  # the source of keys read on this machine (pynput)


class KeyState:
    """Which bound keys are down and for how long since the last `take`; thread-safe, no pynput.

    Fed by the listener thread (press/release with a monotonic time), read by
    the control loop (`take`). Several sources may feed one state (this
    machine's keyboard and browser pages): a key is down while any source
    holds it, so the same physical press seen twice (pynput and a browser on
    the same desktop) moves once, and one source letting go, or going away
    (`release_source`), does not end another's hold.
    """

    def __init__(self, now: float) -> None:
        self._lock = threading.Lock()
        self._down: dict[str, float] = {}
        self._holders: dict[str, set[str]] = {}
        self._held: dict[str, float] = {}
        self._released: dict[str, float] = {}
        self._presses: list[str] = []
        self._last_take = now
        self.last_event_time = 0.0  # monotonic time of the last bound key event
        self.last_press_time = 0.0  # monotonic time a key last went down (not autorepeat, not a release)
        self.last_source: str | None = None  # the source of the newest press

    def press(self, name: str, t: float, source: str = LOCAL) -> None:
        with self._lock:
            self.last_event_time = t
            holders = self._holders.setdefault(name, set())
            if source in holders:
                return  # autorepeat while held
            holders.add(source)
            self.last_source = source
            self.last_press_time = t
            if name in self._down:
                return  # already held by another source
            self._down[name] = t
            if t - self._released.get(name, -1e9) > REPEAT_GAP:
                self._presses.append(name)

    def release(self, name: str, t: float, source: str = LOCAL) -> None:
        with self._lock:
            self.last_event_time = t
            self._release(name, t, source)

    def _release(self, name: str, t: float, source: str) -> None:
        holders = self._holders.get(name)
        if holders:
            holders.discard(source)
            if holders:
                return  # another source still holds it
        self._holders.pop(name, None)
        start = self._down.pop(name, None)
        self._released[name] = t
        if start is not None:
            self._held[name] = self._held.get(name, 0.0) + t - max(start, self._last_take)

    def release_source(self, source: str, t: float) -> list[str]:
        """Let go of every key `source` holds (it lost focus or went away); returns their names."""
        with self._lock:
            names = [name for name, holders in self._holders.items() if source in holders]
            for name in names:
                self._release(name, t, source)
            return names

    def holding(self) -> dict[str, list[str]]:
        """source -> the keys it holds now."""
        with self._lock:
            out: dict[str, list[str]] = {}
            for name, holders in self._holders.items():
                for source in holders:
                    out.setdefault(source, []).append(name)
            return {source: sorted(names) for source, names in out.items()}

    def take(self, now: float) -> tuple[dict[str, float], list[str]]:
        """(fraction of the time since the last take each key was held, keys newly pressed)."""
        with self._lock:
            held = self._held
            for name, start in self._down.items():
                held[name] = held.get(name, 0.0) + now - max(start, self._last_take)
            interval = now - self._last_take
            presses, self._presses, self._held = self._presses, [], {}
            self._last_take = now
        if interval <= 0:
            return {}, presses
        return {k: min(max(v / interval, 0.0), 1.0) for k, v in held.items() if v > 0}, presses

    def clear(self) -> None:
        with self._lock:
            self._down.clear()
            self._holders.clear()
            self._held.clear()


def environment_problem() -> str | None:
    """Why keys cannot be read here, judged from the environment alone (no import)."""
    if sys.platform.startswith("linux") or "bsd" in sys.platform:
        if not os.environ.get("DISPLAY"):
            if os.environ.get("WAYLAND_DISPLAY"):
                return (
                    "Wayland without X: the keyboard device reads keys through X11 and DISPLAY is not set; "
                    "log in to an X11 session (or enable Xwayland), or drive with the browser gizmo or a SpaceMouse"
                )
            return (
                "no display (DISPLAY is not set): the keyboard device reads keys from an X11 desktop; "
                "run teleop inside one, or drive with the browser gizmo (teleop serve) or a SpaceMouse"
            )
    return None


def wayland_note() -> str:
    """A caveat for X11-under-Wayland sessions, where native Wayland windows hide their keys."""
    if os.environ.get("WAYLAND_DISPLAY") or os.environ.get("XDG_SESSION_TYPE") == "wayland":
        return (
            "Wayland session: keys typed into native Wayland windows (most browsers) do not reach teleop; "
            "keep an X11 (Xwayland) window focused, e.g. an xterm, or log in to an X11 session"
        )
    return ""


def _import_problem(exc: BaseException) -> str:
    text = str(exc)
    display = os.environ.get("DISPLAY", "")
    if "Bad display name" in text or "DisplayNameError" in text:
        return f"DISPLAY={display!r} is not a valid X display name; set it to your desktop's display (e.g. :0)"
    if "uthoriz" in text:
        return (
            f"X display {display} refused the connection (authorization): run teleop as the desktop's user "
            "or set XAUTHORITY to its cookie file"
        )
    if "connect" in text.lower():
        return (
            f"cannot connect to X display {display} (is its X server running? check DISPLAY); "
            "or drive with the browser gizmo or a SpaceMouse"
        )
    return f"pynput cannot read the keyboard here: {text.splitlines()[0] if text else type(exc).__name__}"


def import_pynput_keyboard():
    """Import pynput.keyboard, turning its display failures into a one-line DeviceError."""
    problem = environment_problem()
    if problem:
        raise DeviceError(problem)
    try:
        from pynput import keyboard
    except ImportError as exc:
        if exc.name == "pynput":
            raise DeviceError("the pynput package is missing: pip install pynput") from None
        raise DeviceError(_import_problem(exc)) from None
    except Exception as exc:  # Xlib raises its own errors on some failures
        raise DeviceError(_import_problem(exc)) from None
    _check_x_display()
    return keyboard


def _check_x_display() -> None:
    """Connect to the X display now: pynput checks only at its first import, and the
    listener thread would otherwise fail silently if the display has gone since."""
    if not (sys.platform.startswith("linux") or "bsd" in sys.platform):
        return
    try:
        from Xlib import display as xdisplay

        xdisplay.Display().close()
    except ImportError:
        return  # pynput runs on another backend (uinput); nothing to check here
    except Exception as exc:
        raise DeviceError(_import_problem(exc)) from None


def _key_name(key, listener) -> str | None:
    """pynput key -> binding name ('w', 'space', 'enter', '=', ...), None if unbound."""
    from pynput.keyboard import Key, KeyCode

    if isinstance(key, Key):
        name = key.name
    else:
        key = listener.canonical(key)
        name = key.char.lower() if isinstance(key, KeyCode) and key.char else None
    name = ALIASES.get(name, name)
    return name if name in KEY_ACTION else None


class KeyboardDevice:
    """Keys -> Commands for one arm at a time (tab switches arm in a bimanual scene)."""

    kind = "keyboard"

    def __init__(self, pos_speed: float = 0.15, rot_speed: float = 0.8, n_arms: int = 1, name: str = "keyboard") -> None:
        self.name = name
        self.pos_speed = pos_speed
        self.rot_speed = rot_speed
        self.n_arms = n_arms
        self.arm = 0
        self.frame = "world"
        self.speed_scale = 1.0
        self.warning = ""  # a caveat found at start (Wayland), for the session to print
        self.keys = KeyState(time.monotonic())
        self._listener = None
        self._modifiers: set[str] = set()
        self._closed = False

    @property
    def last_event_time(self) -> float:
        """time.monotonic() when the listener last saw a bound key (0 if never)."""
        return self.keys.last_event_time

    def start(self) -> None:
        keyboard = import_pynput_keyboard()
        listener = keyboard.Listener(on_press=self._on_press, on_release=self._on_release)
        self._listener = listener
        self.keys = KeyState(time.monotonic())
        listener.start()
        ready = threading.Event()
        threading.Thread(target=lambda: (listener.wait(), ready.set()), daemon=True).start()
        if not ready.wait(READY_TIMEOUT) or not listener.is_alive():
            listener.stop()
            raise DeviceError(
                f"the key listener did not start on display {os.environ.get('DISPLAY', '?')} "
                "(an X server without the RECORD extension?); use the browser gizmo or a SpaceMouse"
            )
        if sys.platform == "darwin" and getattr(listener, "IS_TRUSTED", True) is False:
            listener.stop()
            raise DeviceError(
                "macOS does not let this app read the keyboard: System Settings > Privacy & Security > "
                "Accessibility and Input Monitoring: allow your terminal, then restart it"
            )
        self.warning = wayland_note() if sys.platform.startswith("linux") else ""

    def _on_press(self, key) -> None:
        modifier = getattr(key, "name", None)
        if modifier in MODIFIERS:
            self._modifiers.add(modifier)
            return
        name = _key_name(key, self._listener)
        if name is not None and not self._modifiers:  # Ctrl+W, Alt+Tab... belong to other apps
            self.keys.press(name, time.monotonic())

    def _on_release(self, key) -> None:
        modifier = getattr(key, "name", None)
        if modifier in MODIFIERS:
            self._modifiers.discard(modifier)
            return
        name = _key_name(key, self._listener)
        if name is not None:
            self.keys.release(name, time.monotonic())

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        """One-shot keys pressed since the last tick, then the held keys' motion for this tick."""
        held, presses = self.keys.take(time.monotonic())
        events: list[str] = []
        grippers = 0
        n_arms = max(int(view.n_arms), 1) if view is not None else self.n_arms  # None: polled without a session (bench)
        for name in presses:
            action = KEY_ACTION[name]
            if action == "gripper":
                grippers += 1
            elif action in ("reset", "start", "save", "discard", "policy"):
                events.append(action)
            elif action == "arm":
                self.arm = (self.arm + 1) % n_arms
            elif action == "frame":
                self.frame = "ee" if self.frame == "world" else "world"
            elif action == "faster":
                self.speed_scale = min(self.speed_scale * SPEED_STEP, SPEED_LIMITS[1])
            elif action == "slower":
                self.speed_scale = max(self.speed_scale / SPEED_STEP, SPEED_LIMITS[0])
        self.arm = min(self.arm, n_arms - 1)
        deltas = {"translation": np.zeros(3), "rotation": np.zeros(3)}
        speeds = {"translation": self.pos_speed, "rotation": self.rot_speed}
        for name, fraction in held.items():
            motion = MOTION.get(KEY_ACTION[name])
            if motion is not None:
                delta, axis, sign = motion
                deltas[delta][axis] += sign * speeds[delta] * self.speed_scale * dt * fraction
        first = Command(
            translation=deltas["translation"],
            rotation=deltas["rotation"],
            frame=self.frame,
            gripper="toggle" if grippers else None,
            arm=self.arm,
            events=tuple(events),
            source=self.name,
        )
        commands = [] if first.is_idle() else [first]
        commands += [Command(gripper="toggle", arm=self.arm, source=self.name) for _ in range(grippers - 1)]
        return commands

    def status(self) -> str:
        if self._closed:
            return "closed"
        if self._listener is None:
            return "not started"
        return "connected" if self._listener.is_alive() else "disconnected"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._closed = True
        if self._listener is not None:
            # On X11 the listener thread only notices stop() at the next key event;
            # it is a daemon thread, so it does not hold the process open.
            self._listener.stop()
        self.keys.clear()
