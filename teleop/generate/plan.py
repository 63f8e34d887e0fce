"""One generated demonstration: source segments moved into a new scene and executed.

MimicGen's method, on our recordings. A source episode is cut into its
object-centric subtasks (replay.subtasks.sidecar); each subtask's segment keeps
the EE target poses the operator drove (world frame) and the pose of the
subtask's reference object at the segment's first step. In a new scene, when a
subtask begins, its segment is carried into the object's new pose,

    T_ee_new(t) = T_obj_new @ inv(T_obj_src) @ T_ee_src(t),

reached from where the arm is by a smooth interpolation (lifted in an arc, so
a held object clears the table), and followed tick by tick with the source's
gripper commands, through the same Controller a person drives.

`PlanDevice` is the device that does this, so a generated episode runs through
`run_episode` and is recorded like any other.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from devices.command import Command
from devices.script import slerp
from replay.episode import Episode
from replay.subtasks.sidecar import Subtask
from scenes.tasks.registry import object_pose

REACH_SPEED = 0.2  # m/s on average of the interpolation to a segment's first pose (a held object stays held)
TURN_SPEED = 1.5  # rad/s of the same
MIN_REACH_S = 0.3  # s, the shortest interpolation (a held object is not jerked)
ARC_HEIGHT = 0.06  # m, at most, that the interpolation rises above the straight line
LIFT_CLEARANCE = 0.06  # m the EE rises after a grasp before the next subtask's segment takes over
SETTLE_S = 1.0  # s held at the last pose for the task to succeed (objects come to rest)


def homogeneous(pos: np.ndarray, mat: np.ndarray) -> np.ndarray:
    """4x4 transform from a position (m) and a 3x3 rotation."""
    out = np.eye(4)
    out[:3, :3] = mat
    out[:3, 3] = pos
    return out


def pose_to_matrix(pose: np.ndarray) -> np.ndarray:
    """(x, y, z, qw, qx, qy, qz) -> 4x4."""
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, np.asarray(pose[3:7], dtype=float))
    return homogeneous(pose[:3], mat.reshape(3, 3))


def matrix_to_pose(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """4x4 -> (position (3,), wxyz quaternion (4,))."""
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, np.ascontiguousarray(t[:3, :3]).reshape(9))
    return t[:3, 3].copy(), quat


def _angle(q0: np.ndarray, q1: np.ndarray) -> float:
    return 2.0 * math.acos(min(1.0, abs(float(np.dot(q0, q1)))))


def reach_ticks(p0: np.ndarray, q0: np.ndarray, p1: np.ndarray, q1: np.ndarray, dt: float) -> int:
    """Ticks (of dt s) of the interpolation from pose 0 to pose 1, at REACH_SPEED / TURN_SPEED, MIN_REACH_S at least."""
    dist = float(np.linalg.norm(p1 - p0))
    return max(int(math.ceil(max(dist / REACH_SPEED, _angle(q0, q1) / TURN_SPEED, MIN_REACH_S) / dt)), 1)


def reach_path(p0: np.ndarray, q0: np.ndarray, p1: np.ndarray, q1: np.ndarray, n: int) -> list[tuple[np.ndarray, np.ndarray]]:
    """n poses (position m, wxyz quaternion) from pose 0 to pose 1: smoothstep in time, lifted in an arc."""
    arc = min(ARC_HEIGHT, 0.5 * float(np.linalg.norm(p1 - p0)))
    out = []
    for i in range(1, n + 1):
        u = i / n
        s = u * u * (3.0 - 2.0 * u)  # smoothstep: starts and ends at rest
        p = p0 + s * (p1 - p0)
        p[2] += arc * math.sin(math.pi * s)
        out.append((p, slerp(q0, q1, s)))
    return out


@dataclass(frozen=True)
class Segment:
    """One subtask of one source episode, ready to be carried into a new scene."""

    source: str  # the source episode's path, as given
    object: str  # reference body, site or geom
    poses: np.ndarray  # (n, 4, 4) EE target poses, world frame of the source scene
    gripper_open: np.ndarray  # (n,) bool, the commanded gripper at each step
    object_pose: np.ndarray  # (4, 4) the object's world pose at the segment's first step (source scene)


def execution_bounds(episode: Episode, subtasks: Sequence[Subtask], arm: int = 0) -> list[int]:
    """Where generation switches from one segment to the next: each boundary, moved on past the lift.

    An annotated grasp ends when the fingers close, with the object still on the
    table; the source's next motion (lifting it) belongs to where the object is,
    not to the next subtask's object. As Isaac Lab Mimic's subtask term offsets
    do, the switch moves on until the EE target has risen LIFT_CLEARANCE above
    its height at the boundary (or to its highest point before the next one),
    so the next segment begins in the air and a carried object clears the table.
    """
    z = episode.ee_target[:, arm, 2]
    bounds = [s.start for s in subtasks] + [subtasks[-1].end]
    out = [0]
    for i in range(1, len(subtasks)):
        b, limit = bounds[i], bounds[i + 1] - 1
        rise = np.nonzero(z[b:limit] >= z[b] + LIFT_CLEARANCE)[0]
        out.append(b + int(rise[0]) if len(rise) else b + int(np.argmax(z[b:limit])) if limit > b else b)
    return out + [bounds[-1]]


def segments_of(episode: Episode, subtasks: Sequence[Subtask], arm: int = 0) -> list[Segment]:
    """Cut a source episode into one Segment per subtask (switching at `execution_bounds`)."""
    model = episode.build_model()
    data = mujoco.MjData(model)
    bounds = execution_bounds(episode, subtasks, arm)
    out = []
    for i, sub in enumerate(subtasks):
        start, end = bounds[i], bounds[i + 1]
        mujoco.mj_setState(model, data, episode.state[start], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_kinematics(model, data)
        pos, mat = object_pose(model, data, sub.object)
        targets = episode.ee_target[start:end, arm]
        out.append(Segment(
            source=str(episode.path),
            object=sub.object,
            poses=np.stack([pose_to_matrix(p) for p in targets]),
            gripper_open=episode.gripper[start:end, arm] >= 0.5,
            object_pose=homogeneous(pos, mat),
        ))
    return out


NEAR_M = 0.1  # m: sources whose carried start is within this of the nearest one are equally good


def choose_segments(session, candidates: Sequence[Sequence[Segment]], rng: np.random.Generator,
                    arm: int = 0) -> list[Segment]:
    """Pick one source segment per subtask, before the episode starts.

    For each subtask, every source's segment is carried into the object's pose in
    this scene, and one is drawn among those whose first pose lies nearest
    (within NEAR_M of the nearest) to where the arm will be: its target now for
    the first subtask, the previous chosen segment's carried last pose after
    that. A segment recorded from the other side of its object would otherwise
    send the arm on a long detour with the object in hand (MimicGen's
    nearest-neighbour selection, measured on the robot's side).
    """
    here = pose_to_matrix(np.concatenate(session.controller.target_pose(arm)))
    chosen = []
    for options in candidates:
        carried = []
        for seg in options:
            pos, mat = object_pose(session.controller.model, session.controller.data, seg.object)
            carried.append(homogeneous(pos, mat) @ np.linalg.inv(seg.object_pose) @ seg.poses[[0, -1]])
        dist = np.array([np.linalg.norm(c[0][:3, 3] - here[:3, 3]) for c in carried])
        near = np.nonzero(dist <= dist.min() + NEAR_M)[0]
        pick = int(near[rng.integers(len(near))])
        chosen.append(options[pick])
        here = carried[pick][1]
    return chosen


class PlanDevice:
    """Drives one arm through chosen source segments, each carried into the scene as it begins.

    The object pose is read when its subtask begins (not at the episode's
    start): a place subtask is relative to where the target object is then.
    """

    kind = "generated"

    def __init__(self, session, segments: Sequence[Segment], arm: int = 0, settle_s: float = SETTLE_S) -> None:
        self.name = "generator"
        self.session = session  # the app's Session: its model and data give object poses
        self.segments = list(segments)
        self.arm = arm
        self.settle_ticks = max(1, int(round(settle_s / session.dt)))
        self._queue: list[tuple[np.ndarray, np.ndarray, bool]] = []
        self._next = 0
        self._settled = 0
        self._gripper_open: bool | None = None
        self.planned_steps = 0

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def status(self) -> str:
        return "done" if self.finished else f"subtask {self._next}/{len(self.segments)}"

    @property
    def finished(self) -> bool:
        done = self._next >= len(self.segments) and not self._queue
        return done and (self._settled >= self.settle_ticks or (self._settled > 0 and self.session.controller.success()))

    def _plan(self, seg: Segment) -> None:
        """Queue the interpolation to `seg` carried into the object's current pose, then the segment."""
        pos, mat = object_pose(self.session.controller.model, self.session.controller.data, seg.object)
        moved = homogeneous(pos, mat) @ np.linalg.inv(seg.object_pose) @ seg.poses
        p0, q0 = self.session.controller.target_pose(self.arm)
        p1, q1 = matrix_to_pose(moved[0])
        n = reach_ticks(p0, q0, p1, q1, self.session.dt)
        hold = self._gripper_open if self._gripper_open is not None else bool(seg.gripper_open[0])
        self._queue.extend((p, q, hold) for p, q in reach_path(p0, q0, p1, q1, n))
        for t, open_ in zip(moved, seg.gripper_open):
            p, q = matrix_to_pose(t)
            self._queue.append((p, q, bool(open_)))
        self.planned_steps += n + len(moved)

    def poll(self, view, dt: float) -> list[Command]:
        if not self._queue and self._next < len(self.segments):
            self._plan(self.segments[self._next])
            self._next += 1
        if not self._queue:
            self._settled += 1
            return []
        p, q, open_ = self._queue.pop(0)
        commands = [Command(target_pos=p, target_quat=q, arm=self.arm, source=self.name)]
        if open_ != self._gripper_open:
            commands.append(Command(gripper="open" if open_ else "close", arm=self.arm, source=self.name))
            self._gripper_open = open_
        return commands
