"""Editing an episode's subtask boundaries by hand: what the replay viewer's Subtasks panel does.

All positions are steps (control ticks): a boundary at step b ends one subtask
(exclusive) and starts the next there. Every edit keeps the subtasks contiguous
and non-empty, so what is saved always passes `check_subtasks`; an edit that
would break that is refused with an EditRefused whose message is one line.
"""

from __future__ import annotations

from collections.abc import Sequence

import mujoco

from replay.episode import Episode
from replay.errors import first_line
from replay.subtasks.annotate import auto_subtasks, task_subtasks
from replay.subtasks.sidecar import AnnotationError, Subtask, by_arm, from_boundaries, read_subtasks, sidecar_path
from scenes.tasks.constraints import per_arm


class EditRefused(AnnotationError):
    """An edit that would leave an empty or overlapping subtask; nothing was changed."""


class SubtaskEdits:
    """The subtasks being edited: a list of (object, start, end) covering 0..steps.

    A two-arm episode's subtasks are edited one arm at a time: `subtasks` are the chosen
    arm's (`select_arm`), `all_subtasks` every arm's, as they are saved.
    """

    def __init__(self, subtasks: Sequence[Subtask], steps: int) -> None:
        self.steps = int(steps)
        self.arms: dict[str, list[Subtask]] = by_arm(subtasks) or {"": []}
        self.arm = next(iter(self.arms))

    @property
    def subtasks(self) -> list[Subtask]:
        """The chosen arm's subtasks (a one-arm episode's all)."""
        return self.arms[self.arm]

    @subtasks.setter
    def subtasks(self, value: Sequence[Subtask]) -> None:
        self.arms[self.arm] = list(value)

    @property
    def all_subtasks(self) -> list[Subtask]:
        """Every arm's subtasks, one arm after the other: what is saved."""
        return [s for subs in self.arms.values() for s in subs]

    def select_arm(self, arm: str) -> None:
        """Edit `arm`'s subtasks from now on."""
        if arm not in self.arms:
            raise EditRefused(f"no arm {arm!r} is annotated (arms: {', '.join(self.arms)})")
        self.arm = arm

    @property
    def boundaries(self) -> list[int]:
        """The steps where a subtask starts, the first (step 0) excepted."""
        return [s.start for s in self.subtasks[1:]]

    def index_at(self, step: int) -> int:
        """Which subtask holds `step` (clamped to the episode)."""
        step = min(max(int(step), 0), self.steps - 1)
        return next(i for i, s in enumerate(self.subtasks) if s.start <= step < s.end)

    def _rebuild(self, objects: Sequence[str], ends: Sequence[int]) -> None:
        self.subtasks = from_boundaries(objects, ends, self.steps, self.arm)

    def _check_boundary(self, i: int) -> None:
        if not 0 <= i < len(self.subtasks) - 1:
            raise EditRefused(f"there is no boundary {i + 1} (the subtasks have {len(self.subtasks) - 1})")

    def move(self, i: int, step: int) -> None:
        """Put boundary i (between subtask i and i + 1) at `step`, strictly inside its neighbours."""
        self._check_boundary(i)
        lo, hi = self.subtasks[i].start, self.subtasks[i + 1].end
        if not lo < step < hi:
            raise EditRefused(f"boundary {i + 1} must stay between steps {lo} and {hi} (exclusive), not at step {step}")
        ends = self.boundaries
        ends[i] = int(step)
        self._rebuild([s.object for s in self.subtasks], ends)

    def add(self, step: int, obj: str) -> int:
        """Split the subtask holding `step` there; the later part is relative to `obj`. Returns the new boundary's index."""
        i = self.index_at(step)
        if step <= self.subtasks[i].start:
            raise EditRefused(f"step {step} is already a boundary; move the slider inside a subtask")
        objects = [s.object for s in self.subtasks]
        objects.insert(i + 1, obj)
        ends = self.boundaries
        ends.insert(i, int(step))
        self._rebuild(objects, ends)
        return i

    def remove(self, i: int) -> None:
        """Merge the subtasks either side of boundary i; the merged one keeps the earlier one's object."""
        self._check_boundary(i)
        objects = [s.object for s in self.subtasks]
        del objects[i + 1]
        ends = self.boundaries
        del ends[i]
        self._rebuild(objects, ends)

    def set_object(self, step: int, obj: str) -> int:
        """Make the subtask holding `step` relative to `obj`; returns its index."""
        i = self.index_at(step)
        s = self.subtasks[i]
        self.subtasks[i] = Subtask(obj, s.start, s.end, s.arm)
        return i


def even_split(objects: Sequence[str], steps: int) -> list[Subtask]:
    """One subtask per object, of (nearly) equal length; a single one when the steps cannot hold them all."""
    objects = list(objects) if 0 < len(objects) <= steps else list(objects[:1])
    n = len(objects)
    return from_boundaries(objects, [round(steps * k / n) for k in range(1, n)], steps)


def object_choices(episode: Episode, model: mujoco.MjModel) -> list[str]:
    """Reference objects a subtask may name: the task's declared ones, then the scene's bodies off the robot."""
    try:
        declared = [spec.object for spec in task_subtasks(episode.meta.scene, episode.meta.extra)]
    except AnnotationError:
        declared = []
    robot = set()
    for arm in episode.meta.arms:
        site = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_SITE, arm.ee_site)
        if site < 0:
            continue
        root = int(model.site_bodyid[site])
        while root and int(model.body_parentid[root]) != 0:
            root = int(model.body_parentid[root])
        robot.add(root)
    bodies = []
    for b in range(1, model.nbody):
        top = b
        while int(model.body_parentid[top]) != 0:
            top = int(model.body_parentid[top])
        if top not in robot and model.body(b).name:
            bodies.append(model.body(b).name)
    return list(dict.fromkeys([*declared, *bodies]))


def initial_subtasks(episode: Episode, choices: Sequence[str]) -> tuple[list[Subtask], str, bool]:
    """(subtasks, where they come from, whether they are saved) to start editing from.

    The stored annotations when there are valid ones; else the boundaries found
    from the gripper and contacts; else the task's objects split evenly.
    """
    steps = episode.steps
    problem = ""
    try:
        stored = read_subtasks(episode.path, steps)
    except AnnotationError as exc:
        stored, problem = None, f"stored file ignored: {first_line(exc)}. "
    if stored is not None:
        return stored, f"from {sidecar_path(episode.path).name}", True
    try:
        return auto_subtasks(episode), problem + "found from the gripper commands and contacts", False
    except (AnnotationError, KeyError, IndexError, ValueError) as exc:
        problem += f"not found automatically ({first_line(exc)}). "
    try:
        specs = task_subtasks(episode.meta.scene, episode.meta.extra)
    except AnnotationError:
        return even_split(list(choices[:1]) or ["world"], steps), problem + "split evenly", False
    split = [Subtask(s.object, s.start, s.end, arm)  # a two-arm task: each arm's own subtasks, split evenly
             for arm, group in per_arm(specs).items() for s in even_split([g.object for g in group], steps)]
    return split, problem + "split evenly", False
