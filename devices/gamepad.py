"""A gamepad read by the operator's browser (the Gamepad API's standard mapping), driving one arm.

The page sends the pad's state (axes and button values) whenever it changes;
this device keeps the newest state and turns it into hold-to-move deltas at
`pos_speed` / `rot_speed` at full deflection, like the keyboard and the
SpaceMouse. Button presses are taken as edges when a state arrives, so a
press shorter than a control tick is still seen once.

Standard mapping (Xbox names; PlayStation: A = cross, B = circle, LB/RB = L1/R1,
LT/RT = L2/R2, Back = Share/Select, Start = Options):

    left stick        move x / y (up: +x away from the base; right: -y, the robot's right)
    RT / LT           move up / down (and the right stick's vertical axis, no shoulder held)
    right stick       x: yaw; with LB held: roll (x) and pitch (y); with RB held: yaw (x) and pitch (y)
    A                 toggle the gripper
    B                 reset the scene (new seed)
    Start             record / stop (save)
    Back              discard the episode

A radial deadzone keeps a resting stick still. A state older than STALE_S (the
page stopped sending) counts as released, and the web app releases the pad at
once when the page's channel closes or stops answering: no runaway arm.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from devices.command import Command
from devices.view import SessionView

# Standard mapping indices (https://w3c.github.io/gamepad/#remapping)
LEFT_X, LEFT_Y, RIGHT_X, RIGHT_Y = 0, 1, 2, 3
A, B, X, Y, LB, RB, LT, RT, BACK, START = range(10)
N_AXES, N_BUTTONS = 4, 17  # the standard mapping's counts; extra entries are ignored
DEADZONE = 0.12  # stick radius read as zero (fraction of full deflection)
TRIGGER_DEADZONE = 0.05
# A state older than this counts as released. Generous: the browser's channel releases a page that
# stops answering at once; this is for a page whose timers stall (a loaded machine, a hidden tab).
STALE_S = 2.0
PRESSED_AT = 0.5  # a button value at or above this is pressed

MAPPING: tuple[tuple[str, str], ...] = (
    ("left stick", "move x / y (up: away from the base, right: the robot's right)"),
    ("RT / LT", "move up / down (also the right stick's vertical axis)"),
    ("right stick", "yaw; with LB held roll / pitch; with RB held yaw / pitch"),
    ("A", "toggle the gripper"),
    ("B", "reset the scene (new seed)"),
    ("Start", "record / stop (save)"),
    ("Back", "discard the episode"),
)
BUTTON_ACTIONS = {A: "gripper", B: "reset", START: "record", BACK: "discard"}


def stick(x: float, y: float, deadzone: float = DEADZONE) -> tuple[float, float]:
    """A stick's (x, y) with a radial deadzone, rescaled so output starts at 0 past it and reaches 1."""
    r = math.hypot(x, y)
    if r <= deadzone:
        return 0.0, 0.0
    scale = min((r - deadzone) / (1.0 - deadzone), 1.0) / r
    return x * scale, y * scale


@dataclass
class PadState:
    """One state of a pad as the browser reported it (standard mapping)."""

    axes: np.ndarray  # (N_AXES,) in [-1, 1]
    buttons: np.ndarray  # (N_BUTTONS,) in [0, 1]
    arrived: float  # time.monotonic()


class GamepadDevice:
    """The newest pad state from a browser, as deltas for one arm (see the module's mapping)."""

    kind = "gamepad"

    def __init__(self, name: str = "gamepad", arm: int = 0, pos_speed: float = 0.15, rot_speed: float = 0.8) -> None:
        self.name = name
        self.arm = arm
        self.pos_speed = pos_speed
        self.rot_speed = rot_speed
        self.pad_id = ""  # the browser's name for the pad ("Xbox Wireless Controller ...")
        self.states = 0  # states taken since start
        self.last_input_time = 0.0
        self._state: PadState | None = None
        self._pending: list[str] = []  # button actions pressed since the last poll
        self._lock = threading.Lock()
        self._closed = False

    # -- writer side (the browser's messages, already validated) -----------
    def push(self, axes: Sequence[float], buttons: Sequence[float], pad_id: str = "") -> None:
        """Take a new state; values outside [-1, 1] (axes) or [0, 1] (buttons) are clipped."""
        ax = np.zeros(N_AXES)
        given = np.asarray(list(axes)[:N_AXES], dtype=float)
        ax[: len(given)] = np.clip(np.nan_to_num(given), -1.0, 1.0)
        bt = np.zeros(N_BUTTONS)
        given = np.asarray(list(buttons)[:N_BUTTONS], dtype=float)
        bt[: len(given)] = np.clip(np.nan_to_num(given), 0.0, 1.0)
        now = time.monotonic()
        with self._lock:
            before = self._state.buttons if self._state is not None and now - self._state.arrived < STALE_S else np.zeros(N_BUTTONS)
            for index, action in BUTTON_ACTIONS.items():
                if bt[index] >= PRESSED_AT > before[index]:
                    self._pending.append(action)
            self._state = PadState(ax, bt, now)
            self.pad_id = pad_id[:120]
            self.states += 1

    def release(self) -> None:
        """The browser went away or lost the pad: everything released at once."""
        with self._lock:
            self._state = None

    # -- reader side (control loop) -----------------------------------------
    def start(self) -> None:
        self._closed = False

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        with self._lock:
            state = self._state
            if state is not None and time.monotonic() - state.arrived > STALE_S:
                state = self._state = None
            actions, self._pending = self._pending, []
        commands = [self._action(a) for a in actions]
        if state is None:
            return commands
        self.last_input_time = state.arrived
        motion = self._motion(state, dt)
        if not motion.is_idle():
            commands.append(motion)
        return commands

    def _action(self, action: str) -> Command:
        if action == "gripper":
            return Command(gripper="toggle", arm=self.arm, source=self.name)
        return Command(events=(action,), arm=self.arm, source=self.name)

    def _motion(self, state: PadState, dt: float) -> Command:
        lx, ly = stick(state.axes[LEFT_X], state.axes[LEFT_Y])
        rx, ry = stick(state.axes[RIGHT_X], state.axes[RIGHT_Y])
        b = state.buttons
        up = max(b[RT] - TRIGGER_DEADZONE, 0.0) / (1 - TRIGGER_DEADZONE)
        down = max(b[LT] - TRIGGER_DEADZONE, 0.0) / (1 - TRIGGER_DEADZONE)
        roll = pitch = yaw = 0.0
        if b[LB] >= PRESSED_AT:
            roll, pitch = rx, -ry
        elif b[RB] >= PRESSED_AT:
            yaw, pitch = -rx, -ry
        else:
            yaw = -rx
            up, down = up + max(-ry, 0.0), down + max(ry, 0.0)  # the stick's up is -y in the Gamepad API
        # World frame, operator behind the robot: stick up = +x (away), stick right = -y (robot's right).
        translation = np.array([-ly, -lx, np.clip(up, 0, 1) - np.clip(down, 0, 1)]) * self.pos_speed * dt
        rotation = np.array([roll, pitch, yaw]) * self.rot_speed * dt
        return Command(translation=translation, rotation=rotation, arm=self.arm, source=self.name)

    def status(self) -> str:
        if self._closed:
            return "closed"
        with self._lock:
            live = self._state is not None and time.monotonic() - self._state.arrived <= STALE_S
        return f"{self.pad_id or 'gamepad'} (in a browser)" if live else "no pad in any browser"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._closed = True
        self.release()
