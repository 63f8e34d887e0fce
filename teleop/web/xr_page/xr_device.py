"""The headset's controllers and hands as one device (`xr`): EE targets while a clutch is held.

Frames: the XR page sends each hand's pose already in the world frame (MuJoCo's: z up, m), mapped
through the placement it drew the scene with, so what the operator sees and what they move are one
frame. While a hand's clutch (a controller's squeeze, a tracked hand's middle-thumb pinch) is held,
its motion and rotation since the press are applied to its arm's EE target at the press:
    target_pos = target_pos_at_press + scale * (pos - pos_at_press)
    target_quat = (quat * conj(quat_at_press)) * target_quat_at_press      (world frame)
so the arm never jumps at engagement and never moves while its clutch is up.

Which hand drives which arm: one arm, the right hand (the left is free); two arms, left -> arm 0,
right -> arm 1. Safety (all counted in `counts`): a hand that loses tracking, a page hidden by the
system menu (`visible-blurred`), closing, or going quiet, or no pose for STALE_S: that arm's clutch
lets go and the arm holds its target. A NaN or absurd pose is dropped (never reaches IK) and lets go
too; the clutch takes hold again at the next good pose while still held (again from there: no jump).
A target more than MAX_STEP_M from the arm's current target in one tick is refused, the arm held,
and the clutch taken again from where the hand is.
"""

from __future__ import annotations

import collections
import math
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from devices.command import Command
from devices.phone import quat_conj, quat_mul
from devices.view import SessionView

NAME = "xr"
STALE_S = 0.25  # no pose for this long: the hand's clutch lets go
MAX_STEP_M = 0.05  # a target jump larger than this in one tick is refused
MAX_ABS_M = 20.0  # a position farther than this from the world origin is absurd
OPENING_STEP = 0.005  # a gripper opening that moved less than this is not sent again


@dataclass
class _Hand:
    """One controller's (or tracked hand's) newest state, and its clutch's anchor."""

    pos: np.ndarray | None = None
    quat: np.ndarray | None = None
    clutch: bool = False
    opening: float | None = None
    sent_opening: float | None = None
    frame: int = -1
    frame_ms: float = 0.0  # when the page's XR frame that saw this pose began (ms since the epoch)
    arrived: float = 0.0
    mode: str = "controller"
    anchor: tuple | None = None  # (hand pos, hand quat, target pos, target quat) at the press
    fresh: bool = False  # a pose arrived since the last tick


@dataclass
class Counts:
    """What the safety rules did (the status and the tests read them)."""

    bad_poses: int = 0  # NaN or absurd poses dropped
    jumps: int = 0  # target jumps over MAX_STEP_M refused
    releases: dict = field(default_factory=dict)  # why -> clutches let go for it


class XrDevice:
    """EE targets and grippers from the XR page's controllers or hands (module docstring)."""

    kind = "xr"

    def __init__(self, n_arms: int = 1, name: str = NAME, scale: float = 1.0) -> None:
        self.name = name
        self.n_arms = max(1, int(n_arms))
        self.scale = scale  # robot metres per metre the hand moves
        self.counts = Counts()
        self.poses = 0
        self.last_input_time = 0.0  # devices.base.InputStamped: the newest applied pose's arrival
        self.applied_frame = -1  # the page's frame number of the newest pose a tick applied
        self.frame_to_tick_ms: collections.deque[float] = collections.deque(maxlen=200)
        self._hands = {"left": _Hand(), "right": _Hand()}
        self._pending: list[Command] = []
        self._lock = threading.Lock()
        self._closed = False

    def arm_of(self, hand: str) -> int | None:
        """The arm a hand drives: None for the free left hand of a one-arm robot."""
        if self.n_arms >= 2:
            return 0 if hand == "left" else 1
        return 0 if hand == "right" else None

    # -- writer side (the XR page's messages, already parsed) -----------------
    def _let_go(self, hand: _Hand, why: str) -> None:
        if hand.anchor is not None or hand.clutch:
            self.counts.releases[why] = self.counts.releases.get(why, 0) + 1
        hand.anchor, hand.clutch = None, False

    def push_pose(self, hand: str, frame: int, tracked: bool, pos, quat, clutch: bool, opening: float | None,
                  mode: str = "controller", frame_ms: float = 0.0) -> bool:
        """One hand's pose (world frame, m, wxyz); False when it was dropped (untracked, NaN or absurd)."""
        now = time.monotonic()
        with self._lock:
            h = self._hands[hand]
            h.mode = mode
            if opening is not None and math.isfinite(opening):
                h.opening = min(1.0, max(0.0, float(opening)))
            if not tracked:
                self._let_go(h, "tracking lost")
                h.pos = h.quat = None
                return False
            p = None if pos is None or any(v is None for v in pos) else np.asarray(pos, dtype=float)
            q = None if quat is None or any(v is None for v in quat) else np.asarray(quat, dtype=float)
            if (p is None or q is None or not np.all(np.isfinite(p)) or not np.all(np.isfinite(q))
                    or np.abs(p).max() > MAX_ABS_M or not 0.9 < np.linalg.norm(q) < 1.1):
                self.counts.bad_poses += 1
                self._let_go(h, "bad pose")
                h.pos = h.quat = None
                return False
            h.pos, h.quat = p, q / np.linalg.norm(q)
            if not clutch:
                h.anchor = None
            h.clutch = bool(clutch)
            h.frame, h.frame_ms, h.arrived, h.fresh = frame, frame_ms, now, True
            self.poses += 1
        return True

    def press(self, hand: str, button: str) -> None:
        """A controller button: A (right) records / saves, B discards; X and Y are the page's (Y recentres)."""
        event = {"a": "record", "b": "discard"}.get(button)
        if event is None:
            return
        with self._lock:
            self._pending.append(Command(events=(event,), arm=0, source=self.name))

    def release(self, why: str) -> None:
        """Every clutch lets go (the page was hidden, ended its session, closed, or went quiet)."""
        with self._lock:
            for h in self._hands.values():
                self._let_go(h, why)
                h.pos = h.quat = None

    # -- reader side (control loop) -----------------------------------------
    def start(self) -> None:
        self._closed = False

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        now = time.monotonic()
        with self._lock:
            commands, self._pending = self._pending, []
            for side, h in self._hands.items():
                arm = self.arm_of(side)
                if arm is None or arm >= view.n_arms:
                    continue
                command = self._hand_command(h, arm, view, now)
                if h.opening is not None and (h.sent_opening is None or abs(h.opening - h.sent_opening) >= OPENING_STEP):
                    h.sent_opening = h.opening
                    command = command or Command(arm=arm, source=self.name)
                    command.gripper_opening = h.opening
                if command is not None:
                    commands.append(command)
        return commands

    def _hand_command(self, h: _Hand, arm: int, view: SessionView, now: float) -> Command | None:
        if h.clutch and now - h.arrived > STALE_S:
            self._let_go(h, "no pose")
        if not h.clutch or h.pos is None or h.quat is None:
            h.anchor = None
            return None
        target_pos, target_quat = (np.array(v, dtype=float) for v in view.target_pose(arm))
        if h.anchor is None:  # pressed (or tracking back) since the last tick: motion counts from here
            h.anchor = (h.pos.copy(), h.quat.copy(), target_pos, target_quat)
            return None
        if not h.fresh:
            return None
        h.fresh = False
        hand_pos, hand_quat, anchor_pos, anchor_quat = h.anchor
        pos = anchor_pos + self.scale * (h.pos - hand_pos)
        turned = quat_mul(h.quat, quat_conj(hand_quat))
        quat = quat_mul(turned, anchor_quat)
        quat /= np.linalg.norm(quat)
        if np.linalg.norm(pos - target_pos) > MAX_STEP_M:
            self.counts.jumps += 1
            h.anchor = (h.pos.copy(), h.quat.copy(), target_pos, target_quat)  # held; motion counts from here
            return None
        self.last_input_time = h.arrived
        self.applied_frame = h.frame
        if h.frame_ms > 0:  # from the XR frame that saw the pose to this tick (same machine's clock: the bench)
            self.frame_to_tick_ms.append(time.time() * 1000.0 - h.frame_ms)
        return Command(target_pos=pos, target_quat=quat, arm=arm, source=self.name)

    def engaged(self) -> dict[str, bool]:
        """Which hands' clutches hold their arm now."""
        with self._lock:
            return {side: h.anchor is not None for side, h in self._hands.items()}

    def status(self) -> str:
        if self._closed:
            return "closed"
        with self._lock:
            live = [f"{side} {h.mode}{' (clutch)' if h.anchor is not None else ''}" for side, h in self._hands.items()
                    if h.pos is not None and time.monotonic() - h.arrived <= 2.0]
        return ("XR: " + ", ".join(live)) if live else "no headset (open /xr in the headset's browser)"

    def status_counts(self) -> dict:
        with self._lock:
            return {"poses": self.poses, "bad_poses": self.counts.bad_poses, "jumps": self.counts.jumps,
                    "releases": dict(self.counts.releases), "engaged": {side: h.anchor is not None for side, h in self._hands.items()},
                    "frame_to_tick_ms": [round(v, 2) for v in list(self.frame_to_tick_ms)[-50:]]}

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._closed = True
        self.release("closed")
