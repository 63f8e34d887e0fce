"""One control step as the session hands it to the recorder, and its packed row form."""

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


def pack(step: StepRecord) -> np.ndarray:
    """Copy a step's numbers into one fresh float64 row (schema.step_layout order).

    A single concatenate is the cheapest copy that also detaches the row from
    arrays the caller will keep mutating (MjData views).
    """
    return np.concatenate(
        (
            (step.time, step.wall_time),
            step.state,
            step.ctrl,
            np.ravel(step.ee_target),
            np.ravel(step.ee_pose),
            step.qpos,
            step.qvel,
            np.ravel(step.gripper),
        ),
        dtype=np.float64,
    )

