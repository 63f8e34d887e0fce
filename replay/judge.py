"""Judge a recorded episode again: its task's success test at every recorded step.

The task comes from the episode alone (its embedded task file, else its scene
name) and the model from its stored XML, so a recording made before task files
(no task units in its model) is judged with the units of its robot's layout.
"""

from __future__ import annotations

import mujoco
import numpy as np

from replay.episode import Episode
from scenes.assembly.build import layout_for
from scenes.assembly.robot import load_robot
from scenes.tasks.file_task import FileTask
from scenes.tasks.geometry import model_units
from scenes.tasks.registry import task_for_episode


class SuccessJudge:
    """The task's success test on one recorded state after another, in step order: call it with each state's
    forward-computed data; True once the test has held for the task's `hold` seconds (of data.time)."""

    def __init__(self, episode: Episode, model: mujoco.MjModel) -> None:
        task = task_for_episode(episode.meta.scene, episode.meta.extra)
        if isinstance(task, FileTask):
            units = model_units(model)
            if units is None:  # recorded before task files: the layout of the robot it was recorded with
                layout = layout_for(load_robot(episode.meta.robot))
                units = task.units(layout)
            self.test = task.judge(model, units)
        else:
            self.test = lambda d: task.success(model, d)  # noqa: E731
        self.hold = float(task.hold)
        self.since: float | None = None  # data.time when the test last began to hold

    def __call__(self, data: mujoco.MjData) -> bool:
        ok = bool(self.test(data))
        self.since = (self.since if self.since is not None else float(data.time)) if ok else None
        return ok and float(data.time) - self.since >= self.hold - 1e-9  # type: ignore[operator]


def judge_steps(episode: Episode) -> np.ndarray:
    """(T,) bool: success at each recorded state (the state before step k's ctrl), hold included."""
    model = episode.build_model()
    data = mujoco.MjData(model)
    judge = SuccessJudge(episode, model)
    out = np.zeros(episode.steps, dtype=bool)
    for k in range(episode.steps):
        mujoco.mj_setState(model, data, episode.state[k], mujoco.mjtState.mjSTATE_INTEGRATION)
        mujoco.mj_forward(model, data)
        out[k] = judge(data)
    return out
