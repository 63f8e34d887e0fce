"""Control-loop speed: one IK solve, and one whole control step of Panda lift.

Figures (`measure`), Panda lift at 20 Hz control with 25 physics steps of 2 ms:
  ik_solve_us              one IK solve toward a moving target, median
  control_step_ms          one whole control step (command -> clamp -> IK -> 25 physics steps), median
  physics_step_ms          the bare physics of the same tick: mj_step with the same 25 substeps on
                           the same model, from the session's state before each control step, median
  control_overhead_x       control_step_ms / physics_step_ms: how close the loop is to the physics
                           limit (1.0 = nothing but physics); both timed in the same run, alternating
                           tick by tick, so a change in machine speed shows in both
  control_realtime_factor  control period / control_step_ms
"""

from __future__ import annotations

import time

import mujoco
import numpy as np

from devices.command import Command


def _circle(i: int, radius: float = 0.08) -> np.ndarray:
    a = i * 0.05
    return np.array([radius * np.cos(a), radius * np.sin(a), 0.04 * np.sin(2 * a)])


def measure(quick: bool = False) -> dict[str, float]:
    from teleop.control.session import Session

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

    # Whole control step, alternating with the bare physics of the same tick: before each
    # control step, mj_step with the same substeps runs on a copy of the session's state.
    scratch = mujoco.MjData(session.model)
    step_ms, physics_ms = [], []
    for i in range(n):
        mujoco.mj_copyData(scratch, session.model, session.data)
        t0 = time.perf_counter()
        mujoco.mj_step(session.model, scratch, nstep=session.substeps)
        physics_ms.append((time.perf_counter() - t0) * 1e3)
        command = Command(target_pos=center + _circle(i), target_quat=quat)
        t0 = time.perf_counter()
        session.step([command])
        step_ms.append((time.perf_counter() - t0) * 1e3)
    control_step_ms = float(np.median(step_ms))
    physics_step_ms = float(np.median(physics_ms))
    return {
        "ik_solve_us": round(float(np.median(solve_us)), 1),
        "control_step_ms": round(control_step_ms, 4),
        "physics_step_ms": round(physics_step_ms, 4),
        "control_overhead_x": round(control_step_ms / physics_step_ms, 2),
        "control_realtime_factor": round(session.dt * 1e3 / control_step_ms, 1),
    }
