"""A phone as a 6-DoF controller, read by its browser (WebXR where it has it, device orientation otherwise).

The phone page sends its pose whenever the sensors report one: the rotation
from the phone's frame to the earth frame (wxyz; earth: x east, y north, z up,
as the DeviceOrientation spec; WebXR poses are converted by the page) and,
with WebXR, a position (m, same frame). Motion counts only while the clutch
button is held, and relative to where the clutch was pressed, like a
SpaceMouse's clutch: press, move the phone, release, move it back freely.

Frames: at the press, the phone's heading (where its top edge points, or its
back camera when held upright) becomes the robot world's +x, so "push the
phone forward" means "away from the robot's base" whichever way the operator
faces. The rotation since the press is applied to the EE target's rotation
in the world frame, the translation (WebXR only) to its position, times
`scale`. A pose older than STALE_S while the clutch is held releases it.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import mujoco
import numpy as np

from devices.command import Command
from devices.view import SessionView

STALE_S = 2.0  # no pose for this long while the clutch is held: released (the web app also releases a page that goes quiet)
UPRIGHT = 0.7  # |top edge's vertical component| above which the back camera gives the heading


def quat_mul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of wxyz quaternions (MuJoCo's)."""
    out = np.empty(4)
    mujoco.mju_mulQuat(out, np.asarray(a, dtype=float), np.asarray(b, dtype=float))
    return out


def quat_conj(q: np.ndarray) -> np.ndarray:
    out = np.empty(4)
    mujoco.mju_negQuat(out, np.asarray(q, dtype=float))
    return out


def rotate(q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """v rotated by the unit quaternion q."""
    out = np.empty(3)
    mujoco.mju_rotVecQuat(out, np.asarray(v, dtype=float), np.asarray(q, dtype=float))
    return out


def yaw_quat(angle: float) -> np.ndarray:
    """Rotation by `angle` rad about +z."""
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])


def heading(q: np.ndarray) -> float:
    """Where the phone points in the horizontal plane (rad from earth +x): its top edge, or its
    back camera (-z of the screen) when it is held upright."""
    top = rotate(q, np.array([0.0, 1.0, 0.0]))
    forward = top if abs(top[2]) < UPRIGHT else rotate(q, np.array([0.0, 0.0, -1.0]))
    return math.atan2(forward[1], forward[0])


@dataclass
class _Clutch:
    """The phone's and the target's poses when the clutch was pressed."""

    phone_quat: np.ndarray
    phone_pos: np.ndarray | None
    target_pos: np.ndarray
    target_quat: np.ndarray
    to_world: np.ndarray  # yaw rotation taking the press-time heading to world +x


class PhoneDevice:
    """EE targets from a phone's motion while its clutch is held (see the module's frames)."""

    kind = "phone"

    def __init__(self, name: str = "phone", arm: int = 0, scale: float = 1.0) -> None:
        self.name = name
        self.arm = arm
        self.scale = scale  # robot metres per metre the phone moves (WebXR)
        self.poses = 0
        self.last_input_time = 0.0
        self.xr = False  # the page reports positions (WebXR)
        self._quat: np.ndarray | None = None
        self._pos: np.ndarray | None = None
        self._clutch_held = False
        self._arrived = 0.0
        self._pending: list[Command] = []
        self._clutch: _Clutch | None = None
        self._lock = threading.Lock()
        self._closed = False

    # -- writer side (the phone page's messages, already validated) ----------
    def push_pose(self, quat, pos=None, clutch: bool = False) -> bool:
        """The phone's rotation (phone -> earth, wxyz) and, with WebXR, position (m); False if not a pose."""
        q = np.asarray(quat, dtype=float)
        if q.shape != (4,) or not np.all(np.isfinite(q)) or not 0.5 < np.linalg.norm(q) < 1.5:
            return False
        p = None
        if pos is not None:
            p = np.asarray(pos, dtype=float)
            if p.shape != (3,) or not np.all(np.isfinite(p)) or np.abs(p).max() > 100.0:
                return False
        with self._lock:
            self._quat, self._pos = q / np.linalg.norm(q), p
            self._clutch_held = bool(clutch)
            self._arrived = time.monotonic()
            self.xr = p is not None
            self.poses += 1
        return True

    def press(self, action: str) -> None:
        """A button on the phone page: "gripper" (toggle) or an episode event."""
        command = Command(gripper="toggle", arm=self.arm, source=self.name) if action == "gripper" else \
            Command(events=(action,), arm=self.arm, source=self.name)
        with self._lock:
            self._pending.append(command)

    def release(self) -> None:
        """The phone page went away: the clutch lets go."""
        with self._lock:
            self._clutch_held = False
            self._quat = None

    # -- reader side (control loop) -----------------------------------------
    def start(self) -> None:
        self._closed = False

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        with self._lock:
            commands, self._pending = self._pending, []
            held = self._clutch_held and self._quat is not None and time.monotonic() - self._arrived <= STALE_S
            quat, pos, arrived = self._quat, self._pos, self._arrived
        if not held:
            self._clutch = None
            return commands
        if self._clutch is None:  # pressed since the last tick: motion counts from here
            target_pos, target_quat = view.target_pose(self.arm)
            self._clutch = _Clutch(quat.copy(), None if pos is None else pos.copy(), np.array(target_pos, dtype=float),
                                   np.array(target_quat, dtype=float), yaw_quat(-heading(quat)))
            return commands
        c = self._clutch
        align = c.to_world
        turned = quat_mul(quat, quat_conj(c.phone_quat))  # earth frame, since the press
        turned_world = quat_mul(quat_mul(align, turned), quat_conj(align))
        target_quat = quat_mul(turned_world, c.target_quat)
        target_pos = c.target_pos
        if pos is not None and c.phone_pos is not None:
            target_pos = c.target_pos + self.scale * rotate(align, pos - c.phone_pos)
        self.last_input_time = arrived
        commands.append(Command(target_pos=target_pos, target_quat=target_quat / np.linalg.norm(target_quat),
                                arm=self.arm, source=self.name))
        return commands

    def status(self) -> str:
        if self._closed:
            return "closed"
        with self._lock:
            live = self._quat is not None and time.monotonic() - self._arrived <= STALE_S
            held = self._clutch_held
        if not live:
            return "no phone page open (open /phone on the phone)"
        return f"phone ({'WebXR' if self.xr else 'orientation'}), clutch {'held' if held else 'up'}"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self._closed = True
        self.release()
