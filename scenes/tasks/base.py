"""What every task is: its objects go into the arena spec, and success is judged from MjData alone.

Judging from MjData (and the model) alone lets a recording be judged again at
replay. Task files (scenes.tasks.file_task) are the one kind of task; this base holds
what the rest of the program reads from a task.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import mujoco
import numpy as np

from scenes.assembly.arena import Layout

SubtaskKind = Literal["grasp", "place", "push"]
SUBTASK_KINDS: tuple[str, ...] = ("grasp", "place", "push")


@dataclass(frozen=True)
class SubtaskSpec:
    """One object-centric subtask of a task (MimicGen's unit of generation).

    object: the body, site or geom whose frame the subtask's motion is relative to.
    kind: how its end is found in a recording: "grasp" ends when the gripper
        closes on the object, "place" when it opens again, "push" runs to the
        episode's end (no gripper event).
    """

    object: str
    kind: SubtaskKind
    arm: str = ""  # which arm runs it ("left" / "right" on the bimanual robot); "" the only arm


def object_pose(model: mujoco.MjModel, data: mujoco.MjData, name: str) -> tuple[np.ndarray, np.ndarray]:
    """(position (3,), rotation matrix (3, 3)) of a body, site or geom in the world frame (m)."""
    for kind, pos, mat in ((mujoco.mjtObj.mjOBJ_BODY, data.xpos, data.xmat), (mujoco.mjtObj.mjOBJ_SITE, data.site_xpos, data.site_xmat),
                           (mujoco.mjtObj.mjOBJ_GEOM, data.geom_xpos, data.geom_xmat)):
        i = mujoco.mj_name2id(model, kind, name)
        if i >= 0:
            return pos[i].copy(), mat[i].reshape(3, 3).copy()
    raise KeyError(f"the scene has no body, site or geom named {name!r}")


@dataclass
class Task:
    """Base task: subclasses add objects, judge success and name their subtasks in order.

    text: the instruction; instructions: paraphrases (seed s uses
    `instruction_for(s)`); robots: built-in robot names the task fits.
    """

    name: str = ""
    summary: str = ""
    text: str = ""
    needs_bimanual: bool = False
    allows_bimanual: bool = False
    subtasks: tuple[SubtaskSpec, ...] = ()
    family: str = "custom"
    instructions: tuple[str, ...] = ()
    robots: tuple[str, ...] = ()
    hold: float = 0.0  # s the success test must stay true; such a task is judged at every control tick
    constraints: tuple = ()  # scenes.tasks.constraints.Constraint between two arms' subtasks

    def supports(self, bimanual: bool) -> bool:
        return self.allows_bimanual if bimanual else not self.needs_bimanual

    def instruction_for(self, seed: int) -> tuple[str, int]:
        """(the instruction used for `seed`, its index in [text] + instructions)."""
        options = (self.text, *self.instructions)
        index = int(seed) % len(options)
        return options[index], index

    def build(self, spec: mujoco.MjSpec, layout: Layout, rng: np.random.Generator) -> dict[str, bytes] | None:
        """Add the task's bodies to `spec`; returns any asset files (name -> bytes) they reference."""
        raise NotImplementedError

    def success(self, model: mujoco.MjModel, data: mujoco.MjData) -> bool:
        raise NotImplementedError

    def initial_joints(self) -> dict[str, float]:
        """Joint positions (rad or m) a reset puts the task's own joints at (an open drawer, say)."""
        return {}
