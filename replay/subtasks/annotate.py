"""Finding an episode's subtask boundaries from what it recorded.

A task names its subtasks in order (scenes.tasks.base.SubtaskSpec). In a recording,
a "grasp" subtask ends when the gripper, commanded closed, has closed on its
object: the first step after the close command at which both fingers (or, for a
one-contact gripper, the gripper) touch the object and the fingers have
stopped moving (the grip is firm before the next subtask moves the arm). A "place" subtask ends when
the gripper, commanded open again, has let go of what it held. A "push"
subtask has no gripper event and runs to the episode's end. The last subtask
always ends at the episode's end.

Contacts come from the recorded states (mj_setState + mj_forward), so the
boundaries are those of what happened, not of what was asked.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import mujoco
import numpy as np

from replay.episode import ArmMeta, Episode, load_episode
from replay.subtasks.sidecar import AnnotationError, Subtask, from_boundaries, read_subtasks, write_subtasks
from scenes.assembly.robot import SceneError
from scenes.tasks.constraints import per_arm
from scenes.tasks.geometry import subtree
from scenes.tasks.registry import SubtaskSpec, task_for_episode

CLOSED_BELOW = 0.5  # commanded gripper opening (1 open .. 0 closed) under which the gripper is closing
SETTLED = 0.05  # gripper actuator speed, as a fraction of its ctrl range per second, under which it has stopped


class NoGraspError(AnnotationError):
    """A source episode in which a subtask's gripper event never happens (named in the message)."""


def task_subtasks(scene: str, extra: Mapping[str, Any] | None = None) -> tuple[SubtaskSpec, ...]:
    """The subtasks the scene's task declares (from the episode's embedded task file, `extra`, when it has one);
    AnnotationError if it declares none."""
    try:
        task = task_for_episode(scene, extra)
    except SceneError:
        task = None
    if task is None or not task.subtasks:
        raise AnnotationError(f"task {scene!r} declares no subtasks to annotate")
    return task.subtasks


def _object_bodies(model: mujoco.MjModel, name: str) -> set[int]:
    """The bodies that make up a reference object (body, or the body of a site or geom)."""
    for kind, owner in ((mujoco.mjtObj.mjOBJ_BODY, None), (mujoco.mjtObj.mjOBJ_SITE, model.site_bodyid),
                        (mujoco.mjtObj.mjOBJ_GEOM, model.geom_bodyid)):
        i = mujoco.mj_name2id(model, kind, name)
        if i >= 0:
            return subtree(model, i if owner is None else int(owner[i]))
    raise AnnotationError(f"the recorded scene has no body, site or geom named {name!r}")


class _Contacts:
    """Which gripper geoms touch an object at a recorded step (states: (T, nstate) mjSTATE_INTEGRATION)."""

    def __init__(self, model: mujoco.MjModel, states: np.ndarray, arm_meta: ArmMeta) -> None:
        self.states = states
        self.model = model
        self.data = mujoco.MjData(self.model)
        site = self.model.site(arm_meta.ee_site).id
        self.gripper = subtree(self.model, int(self.model.site_bodyid[site]))
        self.actuator = self.model.actuator(arm_meta.gripper_actuator).id if arm_meta.gripper_actuator else None
        if self.actuator is not None:
            lo, hi = self.model.actuator_ctrlrange[self.actuator]
            self.settled_speed = SETTLED * max(abs(float(hi - lo)), 1e-6)  # actuator length units per second

    def settled(self, k: int) -> bool:
        """True when the gripper's actuator has stopped moving at step k (fingers closed on something)."""
        if self.actuator is None:
            return True
        self._at(k)
        return abs(float(self.data.actuator_velocity[self.actuator])) < self.settled_speed

    def _at(self, k: int) -> mujoco.MjData:
        """The recorded state of step k, forward-computed (contacts, actuator velocities)."""
        mujoco.mj_setState(self.model, self.data, self.states[k], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(self.model, self.data)
        return self.data

    def touching(self, k: int, bodies: set[int]) -> int:
        """Number of distinct gripper geoms in contact with `bodies` at step k."""
        m, d = self.model, self._at(k)
        geoms = set()
        for c in d.contact[: d.ncon]:
            b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
            if b1 in self.gripper and b2 in bodies:
                geoms.add(int(c.geom1))
            elif b2 in self.gripper and b1 in bodies:
                geoms.add(int(c.geom2))
        return len(geoms)


def _edges(closed: np.ndarray, start: int, to_closed: bool) -> list[int]:
    """Steps >= start where the command changes to closed (or to open)."""
    return [k for k in range(max(start, 1), len(closed)) if closed[k] == to_closed and closed[k - 1] != to_closed]


def arm_names(episode: Episode) -> list[str]:
    """The recorded arms' names, by the prefix of their EE sites ("left", "right"); "" for a robot's only arm."""
    return [a.ee_site.split("/", 1)[0] if "/" in a.ee_site else "" for a in episode.meta.arms]


def auto_subtasks(episode: Episode, specs: Sequence[SubtaskSpec] | None = None, arm: int = 0) -> list[Subtask]:
    """The episode's subtasks, found from its gripper commands and contacts.

    A two-arm task (its subtasks name arms) is annotated per arm, each arm from its
    own gripper and contacts; the result holds one arm's subtasks after the other's.
    Raises NoGraspError naming the file (and the arm) when a grasp (or release) never happens.
    """
    specs = tuple(specs if specs is not None else task_subtasks(episode.meta.scene, episode.meta.extra))
    if not any(s.arm for s in specs):
        return _auto_one_arm(episode, specs, arm, "")
    names = arm_names(episode)
    out: list[Subtask] = []
    for name, group in per_arm(specs).items():
        if name not in names:
            raise AnnotationError(f"{episode.path.name}: the task's {name} arm is not in the recording "
                                  f"(arms: {', '.join(n or 'one' for n in names)})")
        out += _auto_one_arm(episode, group, names.index(name), name)
    return out


def _auto_one_arm(episode: Episode, specs: Sequence[SubtaskSpec], arm: int, arm_name: str) -> list[Subtask]:
    """One arm's subtasks (`arm`: its index among the recorded arms; `arm_name` stored with them)."""
    name = episode.path.name + (f" ({arm_name} arm)" if arm_name else "")
    steps = episode.steps
    if steps < len(specs):
        raise AnnotationError(f"{name}: {steps} steps cannot hold {len(specs)} subtasks")
    if episode.gripper.ndim != 2 or episode.gripper.shape[1] <= arm:
        raise AnnotationError(f"{name}: no gripper commands recorded for arm {arm}")
    for i, spec in enumerate(specs):
        if spec.kind == "push" and i != len(specs) - 1:
            raise AnnotationError(f"{name}: a push subtask ({spec.object}) must be the last")
    model = episode.build_model()
    ends, why = subtask_ends(model, episode.state, episode.gripper[:, arm], episode.meta.arms[arm], specs)
    if why is not None:
        raise NoGraspError(f"{name}: {why}")
    return from_boundaries([s.object for s in specs], ends[: len(specs) - 1], steps, arm_name)


def subtask_ends(
    model: mujoco.MjModel, states: np.ndarray, gripper: np.ndarray, arm_meta: ArmMeta, specs: Sequence[SubtaskSpec],
) -> tuple[list[int], str | None]:
    """The end steps of the gripper subtasks completed in order (the rules of the module doc), and
    why the next one never ended (None: all did; a final push has no end of its own).

    states: (T, nstate) mjSTATE_INTEGRATION per step; gripper: (T,) the commanded opening, 1 open .. 0 closed.
    """
    steps = len(states)
    closed = np.asarray(gripper) < CLOSED_BELOW
    contacts = _Contacts(model, states, arm_meta)
    ends: list[int] = []
    cursor, held = 0, None
    for spec in specs:
        if spec.kind == "push":
            break
        obj = _object_bodies(contacts.model, spec.object)
        end = None
        if spec.kind == "grasp":
            for k_close in _edges(closed, cursor, True):
                opens = _edges(closed, k_close, False)
                stop = opens[0] if opens else steps
                touching = [(k, contacts.touching(k, obj)) for k in range(k_close, stop)]
                both = [k for k, n in touching if n >= 2]
                one = [k for k, n in touching if n >= 1]
                if both or one:
                    first = (both or one)[0]
                    end = next((k for k in range(first, stop) if contacts.settled(k)), first)
                    break
            if end is None:
                return ends, f"no grasp of {spec.object} found (the gripper never closes on it)"
            held = obj
        else:  # place: the gripper opens and lets go of what it held
            opens = _edges(closed, cursor, False)
            if not opens:
                return ends, f"the gripper never opens to place on {spec.object}"
            end = opens[0]
            if held is not None:
                end = next((k for k in range(opens[0], steps) if contacts.touching(k, held) == 0), steps - 1)
        end = min(max(end, cursor + 1), steps - 1)
        ends.append(end)
        cursor = end
    return ends, None


# Why a failed rollout failed (teleop eval): how far it got through the task's subtasks, by the rules above.
FAILURE_REASONS = {
    "never_grasped": "the first grasp never happened",
    "dropped": "grasped, then the object left the fingers without a place (the gripper never opened)",
    "not_placed": "still holding the object at the end (never opened to place it)",
    "not_at_rest": "every subtask done, but a task object still moving at the end",
    "timeout": "every subtask done, objects at rest, and the task still not met in time",
}
AT_REST = 0.02  # m/s: a subtask's object slower than this at the end is at rest


@dataclass(frozen=True)
class Progress:
    """How far a rollout got: the subtasks it completed in order ("grasp cube", "place bin"), and
    for a failed one the reason (a FAILURE_REASONS key; None for a success)."""

    reached: tuple[str, ...]
    reason: str | None


def progress_of(
    model: mujoco.MjModel, states: np.ndarray, gripper: np.ndarray, arm_meta: ArmMeta,
    specs: Sequence[SubtaskSpec], success: bool,
) -> Progress:
    """The subtasks reached (subtask_ends) and, unless `success`, why the rollout failed.

    states: (T, nstate) per step, the last one the end state; gripper: (T,) commanded opening (1 open .. 0 closed).
    A two-arm task's progress is that of its first arm's subtasks (the arm `gripper` and `arm_meta` describe).
    """
    specs = tuple(specs)
    if any(s.arm for s in specs):
        specs = tuple(next(iter(per_arm(specs).values())))
    ends, _ = subtask_ends(model, states, gripper, arm_meta, specs) if specs and len(states) > 1 else ([], None)
    reached = tuple(f"{s.kind} {s.object}" for s in specs[: len(ends)])
    if success:
        return Progress(reached, None)
    pending = [s for s in specs[len(ends):] if s.kind != "push"]
    if pending:
        nxt = pending[0]
        if nxt.kind == "grasp":
            return Progress(reached, "never_grasped")
        held = next((s.object for s in reversed(specs[: len(ends)]) if s.kind == "grasp"), None)
        contacts = _Contacts(model, states, arm_meta)
        if held is not None and contacts.touching(len(states) - 1, _object_bodies(model, held)) == 0:
            return Progress(reached, "dropped")
        return Progress(reached, "not_placed")
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, states[-1], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(model, data)
    velocity = np.zeros(6)
    for spec in specs:
        body = min(_object_bodies(model, spec.object))
        mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, body, velocity, 0)
        if float(np.linalg.norm(velocity[3:])) > AT_REST:
            return Progress(reached, "not_at_rest")
    return Progress(reached, "timeout")


def annotate(path: str | Path, auto: bool = False, save: bool = True) -> tuple[list[Subtask], str]:
    """(subtasks, how) for an episode file: stored ones, else (with auto) found and stored.

    how: "stored" or "auto". Without `auto` and nothing stored, AnnotationError.
    """
    episode = load_episode(path)
    stored = None if auto else read_subtasks(episode.path, episode.steps)
    if stored is not None:
        return stored, "stored"
    if not auto:
        raise AnnotationError(f"{episode.path.name}: not annotated (annotate it automatically, or in the replay viewer)")
    subtasks = auto_subtasks(episode)
    if save:
        write_subtasks(episode.path, subtasks, episode.steps, by="auto")
    return subtasks, "auto"
