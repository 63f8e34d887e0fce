"""One control step as a caller hands it to the recorder, and how it fills a row."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np



@dataclass
class StepRecord:
    """One control step.

    `state` is mj_getState(..., mjSTATE_INTEGRATION) taken before this tick writes
    ctrl (or any other input), so that stepping state k under ctrl k gives state k+1
    exactly: replay restores state 0 and re-steps with each `ctrl`.
    """

    time: float  # sim time before the step
    state: np.ndarray  # float64 (nstate,), before the step
    ctrl: np.ndarray  # (nu,) applied during this step
    ee_target: np.ndarray  # (n_arms, 7) commanded EE target: xyz + quat wxyz
    ee_pose: np.ndarray  # (n_arms, 7) actual EE pose after the step
    qpos: np.ndarray  # (nq,) before the step
    qvel: np.ndarray  # (nv,) before the step
    gripper: np.ndarray  # (n_arms,) commanded opening, 1.0 open .. 0.0 closed
    commands: list = field(default_factory=list)  # Command.to_dict() of this tick, or the Commands themselves (converted on the writer thread)
    wall_time: float = 0.0  # time.time() at the step


def pack_into(row: np.ndarray, step: StepRecord, cols: dict[str, slice]) -> None:
    """Copy a step's numbers into `row` (one float64 row, fields at `cols`).

    Sizes are checked field by field: numpy would otherwise broadcast a
    one-number array across a whole field.
    """
    fields = (
        ("time", step.time), ("wall_time", step.wall_time), ("state", step.state), ("ctrl", step.ctrl),
        ("ee_target", step.ee_target), ("ee_pose", step.ee_pose), ("qpos", step.qpos), ("qvel", step.qvel),
        ("gripper", step.gripper),
    )
    for name, value in fields:
        col = cols[name]
        if np.size(value) != col.stop - col.start:
            raise ValueError(f"{name} has {np.size(value)} numbers, the episode layout needs {col.stop - col.start}")
        row[col] = np.ravel(value)
