"""Control-loop speed: one IK solve, and one whole control step of Panda lift.

`control_step_ms` uses robosuite's default timing (20 Hz control, 25 physics
steps of 2 ms) so the figure compares directly with robosuite's Lift Panda
step (about 13.5 ms on the project's 2-core machine; see shared notes).
"""

from __future__ import annotations

import time

import numpy as np

from teleop.command import Command

ROBOSUITE_LIFT_STEP_MS = 13.5


def _circle(i: int, radius: float = 0.08) -> np.ndarray:
    a = i * 0.05
    return np.array([radius * np.cos(a), radius * np.sin(a), 0.04 * np.sin(2 * a)])


def measure(quick: bool = False) -> dict[str, float]:
    from teleop.session import Session

    n = 300 if quick else 2000
    session = Session("lift", "panda", seed=0, control_hz=20.0)
    assert session.substeps == 25 and abs(session.timestep - 0.002) < 1e-12
    arm = session.arms[0]
    center = arm.target_pos.copy()
    quat = arm.target_quat.copy()

    # Warm up first: the first few hundred milliseconds of a fresh process run
    # up to twice as slow (clock ramp, caches); the figures are steady-state medians.
    for i in range(1000):
        arm.ik.solve(center + _circle(i), quat)
    arm.ik.reset(arm.ik.home)

    # IK alone: one solve toward a moving target.
    solve_us = []
    for i in range(n):
        target = center + _circle(i)
        t0 = time.perf_counter()
        arm.ik.solve(target, quat)
        solve_us.append((time.perf_counter() - t0) * 1e6)
    arm.ik.reset(arm.ik.home)

    # Whole control step: command -> clamp -> IK -> 25 physics steps.
    step_ms = []
    for i in range(n):
        command = Command(target_pos=center + _circle(i), target_quat=quat)
        t0 = time.perf_counter()
        session.step([command])
        step_ms.append((time.perf_counter() - t0) * 1e3)
    control_step_ms = float(np.median(step_ms))
    return {
        "ik_solve_us": round(float(np.median(solve_us)), 1),
        "control_step_ms": round(control_step_ms, 4),
        "control_speedup_vs_robosuite": round(ROBOSUITE_LIFT_STEP_MS / control_step_ms, 1),
        "control_realtime_factor": round(session.dt * 1e3 / control_step_ms, 1),
    }
