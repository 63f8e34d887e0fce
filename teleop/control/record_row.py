"""Filling one recorded row in place on the control thread.

The recorder hands out the next row of its buffer (`EpisodeWriter.claim`); this
writes the step's numbers straight into it, one copy per field and nothing
allocated, because it runs on every control tick. Column positions are looked
up once per episode.
"""

from __future__ import annotations

import time

import mujoco
import numpy as np

INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION


class RowFiller:
    """Writes a session's step into rows laid out as `columns` (the writer's StepLayout.slices)."""

    def __init__(self, columns: dict[str, slice], model: mujoco.MjModel, n_arms: int):
        self.model = model
        c = columns
        self.state = c["state"]
        # mjSTATE_INTEGRATION begins with time, qpos, qvel: those fields are copies of it.
        s0, nq, nv = c["state"].start, model.nq, model.nv
        self.copies = (
            (c["time"], slice(s0, s0 + 1)),
            (c["qpos"], slice(s0 + 1, s0 + 1 + nq)),
            (c["qvel"], slice(s0 + 1 + nq, s0 + 1 + nq + nv)),
        )
        self.wall_time = c["wall_time"].start
        self.control = c["control"].start if "control" in c else None  # who drove the step (0 person, 1 policy)
        self.ctrl = c["ctrl"]
        t0, p0, g0 = c["ee_target"].start, c["ee_pose"].start, c["gripper"].start
        self.arms = [
            (slice(t0 + 7 * i, t0 + 7 * i + 3), slice(t0 + 7 * i + 3, t0 + 7 * i + 7),
             slice(p0 + 7 * i, p0 + 7 * i + 3), slice(p0 + 7 * i + 3, p0 + 7 * i + 7), g0 + i)
            for i in range(n_arms)
        ]

    def capture_state(self, row: np.ndarray, data: mujoco.MjData) -> None:
        """The state before the tick changes anything (replay steps from it under this ctrl)."""
        mujoco.mj_getState(self.model, data, row[self.state], INTEGRATION)

    def finish(self, row: np.ndarray, data: mujoco.MjData, arms, control: float | None = None) -> None:
        """After the physics step: ctrl applied, targets, the EE poses reached, grippers, who drove."""
        row[self.wall_time] = time.time()
        if self.control is not None:
            row[self.control] = 0.0 if control is None else control
        for dst, src in self.copies:
            row[dst] = row[src]
        row[self.ctrl] = data.ctrl
        for (tp, tq, pp, pq, g), arm in zip(self.arms, arms):
            row[tp] = arm.target_pos
            row[tq] = arm.target_quat
            row[pp] = data.site_xpos[arm.site_id]
            mujoco.mju_mat2Quat(row[pq], data.site_xmat[arm.site_id])
            row[g] = 1.0 if arm.gripper_open else 0.0
