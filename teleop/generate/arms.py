"""Two-arm generation: each arm's segments, scheduled in parallel under the task's constraints.

DexMimicGen's ideas (and Isaac Lab Mimic's), from our reading of the method, on our
one-arm generator (teleop.generate.plan):

- Each arm has its own sequence of object-centric subtasks (annotated per arm) and
  runs it on its own: a subtask's segment is carried into the new scene by the pose
  of its own object when it begins. An arm that is done holds its last target.
- Sequential: (A, i) before (B, j): B's subtask j does not begin until A's subtask i
  has ended; until then B holds where its previous subtask left it (the start of the
  segment it waits to run).
- Coordinated: the subtasks of a group begin together, from one source episode and
  one transform (the first listed subtask's object, read once). In the source they are
  cut to one window, from the latest of their starts to the latest of their ends (an
  arm whose own subtask ends sooner holds its last target to the window's end), and
  the reach to the window's first poses takes the same ticks for every arm, so the
  group ends on the same tick with the arms timed against each other as in the source
  (the moment of a handover).

Poses are 4x4 world transforms (m); one tick is one control step.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import mujoco
import numpy as np

from devices.command import Command
from replay.episode import Episode
from replay.subtasks.annotate import arm_names
from replay.subtasks.sidecar import Subtask, by_arm
from scenes.tasks.constraints import Constraint
from scenes.tasks.registry import object_pose
from teleop.generate.plan import (SETTLE_S, Segment, choose_segments, execution_bounds, homogeneous, matrix_to_pose,
                                  pose_to_matrix, reach_path, reach_ticks, segments_of)

Ref = tuple[int, int]  # (arm index among the recorded arms, subtask index among that arm's)


@dataclass(frozen=True)
class ArmSegments:
    """One source episode cut per arm: `segments[k]` are arm k's (a coordinated subtask holds its group's window)."""

    name: str
    arms: tuple[str, ...]  # the recorded arms' names ("left", "right")
    segments: tuple[tuple[Segment, ...], ...]


def arm_refs(constraints: Sequence[Constraint], arms: Sequence[str]) -> list[tuple[str, tuple[Ref, ...]]]:
    """The constraints with arms named by their index among the recorded arms."""
    return [(c.kind, tuple((list(arms).index(a), i) for a, i in c.refs)) for c in constraints]


def without_idle(seg: Segment) -> Segment:
    """The segment without the ticks at its start and end where its arm stood still (target and gripper
    unchanged): a source recorded one arm at a time has the other arm waiting there, and run in
    parallel that wait is not needed (a coordinated window keeps its ticks: the arms' timing is the point)."""
    moving = np.any(np.abs(np.diff(seg.poses, axis=0)) > 1e-9, axis=(1, 2)) | (np.diff(seg.gripper_open) != 0)
    ticks = np.nonzero(moving)[0]
    if not len(ticks):
        return replace(seg, poses=seg.poses[-1:], gripper_open=seg.gripper_open[-1:])
    first, last = int(ticks[0]), int(ticks[-1]) + 2  # from the last still tick before the motion, to the first after it
    return replace(seg, poses=seg.poses[first:last], gripper_open=seg.gripper_open[first:last])


def cut_arms(episode: Episode, subtasks: Sequence[Subtask], constraints: Sequence[Constraint]) -> ArmSegments:
    """Cut a two-arm source into each arm's segments; each coordinated group into its shared window."""
    names = arm_names(episode)
    groups = by_arm(subtasks)
    per_arm: dict[int, list[Segment]] = {}
    bounds: dict[int, list[int]] = {}
    for name, subs in groups.items():
        k = names.index(name)
        per_arm[k] = [without_idle(seg) for seg in segments_of(episode, subs, k)]
        bounds[k] = execution_bounds(episode, subs, k)
    model = episode.build_model()
    data = mujoco.MjData(model)
    for kind, refs in arm_refs(constraints, names):
        if kind != "coordinated":
            continue
        start = max(bounds[k][i] for k, i in refs)
        end = max(bounds[k][i + 1] for k, i in refs)
        obj = per_arm[refs[0][0]][refs[0][1]].object
        mujoco.mj_setState(model, data, episode.state[start], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_kinematics(model, data)
        shared = homogeneous(*object_pose(model, data, obj))
        for k, i in refs:
            ticks = np.clip(np.arange(start, end), bounds[k][i], bounds[k][i + 1] - 1)  # held once its own subtask ends
            per_arm[k][i] = Segment(  # its own object's name, the group's object's pose (ArmsPlanDevice reads that one)
                source=str(episode.path), object=per_arm[k][i].object,
                poses=np.stack([pose_to_matrix(p) for p in episode.ee_target[ticks, k]]),
                gripper_open=episode.gripper[ticks, k] >= 0.5, object_pose=shared)
    arms = tuple(sorted(per_arm))
    return ArmSegments(str(episode.path), tuple(names[k] for k in arms), tuple(tuple(per_arm[k]) for k in arms))


def choose_arm_segments(session, sources: Sequence[ArmSegments], constraints: Sequence[tuple[str, tuple[Ref, ...]]],
                        rng: np.random.Generator, per_arm: bool) -> list[list[Segment]]:
    """Each arm's segments for this scene: all from one source drawn at random (shared), or with
    `per_arm` each arm's own by the one-arm rule (teleop.generate.plan.choose_segments); a
    coordinated group always takes its first subtask's source for every arm in it."""
    n_arms = len(sources[0].segments)
    if not per_arm:
        pick = sources[int(rng.integers(len(sources)))]
        return [list(s) for s in pick.segments]
    chosen = []
    for k in range(n_arms):
        candidates = [[src.segments[k][i] for src in sources] for i in range(len(sources[0].segments[k]))]
        chosen.append(choose_segments(session, candidates, rng, arm=k))
    by_name = {src.name: src for src in sources}
    for kind, refs in constraints:
        if kind == "coordinated":
            source = by_name[chosen[refs[0][0]][refs[0][1]].source]
            for k, i in refs[1:]:
                chosen[k][i] = source.segments[k][i]
    return chosen


class ArmsPlanDevice:
    """Drives every arm through its chosen segments at once, under the constraints (module doc).

    `spans[k]` gives, once run, the tick each of arm k's subtasks began and ended executing.
    """

    kind = "generated"

    def __init__(self, session, segments: Sequence[Sequence[Segment]], constraints: Sequence[tuple[str, tuple[Ref, ...]]],
                 settle_s: float = SETTLE_S) -> None:
        self.name = "generator"
        self.session = session
        self.segments = [list(s) for s in segments]
        self.after: dict[Ref, list[Ref]] = {}  # (arm, subtask) -> the subtasks that must have ended first
        self.together: dict[Ref, tuple[Ref, ...]] = {}  # (arm, subtask) -> its coordinated group
        for kind, refs in constraints:
            if kind == "sequential":
                self.after.setdefault(refs[1], []).append(refs[0])
            else:
                for r in refs:
                    self.together[r] = refs
        n = len(self.segments)
        self.settle_ticks = max(1, int(round(settle_s / session.dt)))
        self._queue: list[list[tuple[np.ndarray, np.ndarray, bool]]] = [[] for _ in range(n)]
        self._next = [0] * n  # the subtask each arm plans next
        self._ended = [0] * n  # subtasks each arm has finished executing
        self._gripper_open: list[bool | None] = [None] * n
        self._tick = 0
        self._settled = 0
        self.spans: list[list[list[int]]] = [[] for _ in range(n)]
        self.planned_steps = 0

    def start(self) -> None:
        pass

    def close(self) -> None:
        pass

    def status(self) -> str:
        return "done" if self.finished else "subtasks " + ", ".join(f"{i}/{len(s)}" for i, s in zip(self._next, self.segments))

    @property
    def finished(self) -> bool:
        done = all(i >= len(s) for i, s in zip(self._next, self.segments)) and not any(self._queue)
        return done and (self._settled >= self.settle_ticks or (self._settled > 0 and self.session.controller.success()))

    def _idle_at(self, ref: Ref) -> bool:
        """Arm ref[0] has nothing queued, is at subtask ref[1], and every subtask that must end first has."""
        k, i = ref
        return (not self._queue[k] and self._next[k] == i < len(self.segments[k])
                and all(self._ended[a] > j for a, j in self.after.get(ref, ())))

    def _begin(self, group: Sequence[Ref]) -> None:
        """Queue each subtask of `group`: the reach to its carried first pose (the same ticks for all), then its poses."""
        ctrl = self.session.controller
        first = self.segments[group[0][0]][group[0][1]]
        obj = homogeneous(*object_pose(ctrl.model, ctrl.data, first.object))  # a group: one object, read once
        carried = {k: obj @ np.linalg.inv(self.segments[k][i].object_pose) @ self.segments[k][i].poses for k, i in group}
        starts = {k: ctrl.target_pose(k) for k, _ in group}
        ends = {k: matrix_to_pose(carried[k][0]) for k, _ in group}
        n = max(reach_ticks(*starts[k], *ends[k], self.session.dt) for k, _ in group)
        for k, i in group:
            seg = self.segments[k][i]
            hold = self._gripper_open[k] if self._gripper_open[k] is not None else bool(seg.gripper_open[0])
            self._queue[k].extend((p, q, hold) for p, q in reach_path(*starts[k], *ends[k], n))
            for t, open_ in zip(carried[k], seg.gripper_open):
                p, q = matrix_to_pose(t)
                self._queue[k].append((p, q, bool(open_)))
            self._next[k] += 1
            self.spans[k].append([self._tick, -1])
            self.planned_steps += n + len(carried[k])

    def poll(self, view, dt: float) -> list[Command]:
        for k in range(len(self.segments)):
            ref = (k, self._next[k])
            if not self._idle_at(ref):
                continue
            group = self.together.get(ref, (ref,))
            if all(self._idle_at(r) for r in group):  # else: hold until every arm of the group is ready
                self._begin(group)
        commands: list[Command] = []
        for k, queue in enumerate(self._queue):
            if not queue:
                continue
            p, q, open_ = queue.pop(0)
            commands.append(Command(target_pos=p, target_quat=q, arm=k, source=self.name))
            if open_ != self._gripper_open[k]:
                commands.append(Command(gripper="open" if open_ else "close", arm=k, source=self.name))
                self._gripper_open[k] = open_
            if not queue:
                self._ended[k] += 1
                self.spans[k][-1][1] = self._tick + 1
        self._tick += 1
        if not commands and all(i >= len(s) for i, s in zip(self._next, self.segments)):
            self._settled += 1
        return commands


def generated_subtasks(device: ArmsPlanDevice, arms: Sequence[str], steps: int) -> list[Subtask]:
    """The generated episode's subtasks per arm: each from the tick its motion began (its reach), the
    last to the episode's end (waiting counts to the subtask before it), for the sidecar file."""
    out = []
    for k, (name, spans) in enumerate(zip(arms, device.spans)):
        starts = [0] + [s[0] for s in spans[1:] if 0 < s[0] < steps] + [steps]
        out += [Subtask(seg.object, starts[i], starts[i + 1], name) for i, seg in enumerate(device.segments[k][: len(starts) - 1])]
    return out


__all__ = ["ArmSegments", "ArmsPlanDevice", "arm_refs", "choose_arm_segments", "cut_arms", "generated_subtasks",
           "without_idle"]
