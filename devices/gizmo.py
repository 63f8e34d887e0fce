"""Gizmo device: end-effector targets dragged in the browser, handed to the control loop.

The web app's gizmo callbacks run on viser's threads while the control loop
polls on its own, so the two meet in a small locked mailbox: `push` keeps
only the newest pose per arm (a drag sends far more poses than there are
control ticks; the ones in between are stale by the time the loop runs) and
`poll` hands each new pose over exactly once as an absolute target.

The device also remembers whether an arm's gizmo is being dragged, so the
web app knows when it may move the gizmo to a target changed by another
device (never under the operator's mouse).
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import numpy as np

from devices.command import Command
from devices.view import SessionView

SETTLE_S = 0.3  # after a drag ends, the gizmo stays where the mouse left it this long


@dataclass
class _Mailbox:
    pos: np.ndarray | None = None
    quat: np.ndarray | None = None
    arrived: float = 0.0  # time.monotonic() of the newest pose
    dragging: bool = False
    ended: float = 0.0  # time.monotonic() of the last drag end


class GizmoDevice:
    """Absolute EE targets from the browser's transform gizmo, one mailbox per arm."""

    kind = "gizmo"

    def __init__(self, n_arms: int = 1, name: str = "gizmo") -> None:
        self.name = name
        self.n_arms = max(int(n_arms), 1)
        self._boxes = [_Mailbox() for _ in range(self.n_arms)]
        self._lock = threading.Lock()
        self._closed = False
        self.clients = 0  # browsers connected (set by the web app, shown as status)
        self.last_input_time = 0.0  # arrival time of the newest pose handed to the loop
        self.drags = 0

    # -- writer side (browser callbacks) ----------------------------------
    def push(self, arm: int, pos, quat, phase: str = "update") -> None:
        """Store the newest gizmo pose for `arm`; phase is viser's "start" | "update" | "end"."""
        if not 0 <= arm < self.n_arms:
            return
        pos = np.asarray(pos, dtype=float).copy()
        quat = np.asarray(quat, dtype=float).copy()
        if pos.shape != (3,) or quat.shape != (4,) or not (np.all(np.isfinite(pos)) and np.all(np.isfinite(quat))):
            return
        now = time.monotonic()
        with self._lock:
            box = self._boxes[arm]
            box.pos, box.quat, box.arrived = pos, quat, now
            if phase == "start":
                box.dragging = True
                self.drags += 1
            elif phase == "end":
                box.dragging = False
                box.ended = now

    def release(self, arm: int | None = None) -> None:
        """End any drag (a browser went away mid-drag)."""
        now = time.monotonic()
        with self._lock:
            for i, box in enumerate(self._boxes):
                if arm is None or arm == i:
                    if box.dragging:
                        box.dragging, box.ended = False, now

    def busy(self, arm: int) -> bool:
        """True while the gizmo is held, has a pose the loop has not taken, or was just let go."""
        with self._lock:
            box = self._boxes[arm]
            return box.dragging or box.pos is not None or time.monotonic() - box.ended < SETTLE_S

    # -- reader side (control loop) ---------------------------------------
    def start(self) -> None:
        self._closed = False

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        commands = []
        with self._lock:
            for arm, box in enumerate(self._boxes):
                if box.pos is None:
                    continue
                commands.append(Command(target_pos=box.pos, target_quat=box.quat, arm=arm, source=self.name))
                self.last_input_time = max(self.last_input_time, box.arrived)
                box.pos = box.quat = None
        return commands

    def status(self) -> str:
        if self._closed:
            return "closed"
        if self.clients <= 0:
            return "no browser"
        return f"{self.clients} browser{'s' if self.clients != 1 else ''}"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._closed = True
