"""Control-loop speed: one IK solve, one whole control step of Panda lift, and robosuite's.

Figures (`measure`), Panda lift at 20 Hz control with 25 physics steps of 2 ms:
  ik_solve_us              one IK solve toward a moving target, median
  control_step_ms          one whole control step (command -> clamp -> IK -> 25 physics steps), median
  physics_step_ms          the bare physics of the same tick: mj_step with the same 25 substeps on
                           a copy of the session's state before the tick, under the ctrl the tick
                           wrote (the very same computation), median
  control_overhead_x       control_step_ms / physics_step_ms: how close the loop is to the physics
                           limit (1.0 = nothing but physics); both timed in the same run, alternating
                           tick by tick, so a change in machine speed shows in both
  tick_overhead_us         what is neither physics nor IK in a tick (command handling, clamp, ctrl
                           write, poses after the step, bookkeeping): per tick, step - physics - IK
                           solve, median
  tick_parts_us            each part of a tick on its own, median (tick_parts): commands, ik, ctrl,
                           physics, poses, judge, errors, rest
  control_realtime_factor  control period / control_step_ms
  robosuite_step_ms        robosuite's own Lift Panda env.step (default OSC controller, 20 Hz,
                           25 x 2 ms), median; timed in blocks alternating with ours in this run.
                           Only when a robosuite interpreter is found (bench/robosuite_lift.py):
                           TELEOP_ROBOSUITE_PYTHON, else .venv-robosuite/bin/python, else this
                           Python if it imports robosuite; absent otherwise
  robosuite_speedup_x      robosuite_step_ms / control_step_ms (same run)
  ik_max_diff_vs_mink      largest |v - v_mink| (rad/s) of the fast IK against mink.solve_ik on
                           IK_CHECKS random reachable targets, limits active and inactive (not with --quick)
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import time
from pathlib import Path

import mujoco
import numpy as np

from devices.command import Command

ROOT = Path(__file__).resolve().parent.parent
WORKER = Path(__file__).resolve().parent / "robosuite_lift.py"
BLOCK = 20  # our ticks between two robosuite blocks
ROBOSUITE_BLOCK = 5  # robosuite steps per block (each ~10x ours)
IK_CHECKS = 10_000


def _circle(i: int, radius: float = 0.08) -> np.ndarray:
    a = i * 0.05
    return np.array([radius * np.cos(a), radius * np.sin(a), 0.04 * np.sin(2 * a)])


def robosuite_python() -> str | None:
    """An interpreter that can run robosuite's Lift, or None."""
    named = os.environ.get("TELEOP_ROBOSUITE_PYTHON")
    if named:
        return named
    local = ROOT / ".venv-robosuite" / "bin" / "python"
    if local.exists():
        return str(local)
    if importlib.util.find_spec("robosuite") is not None:
        return sys.executable
    return None


class RobosuiteLift:
    """robosuite's Lift step running in its own process (bench/robosuite_lift.py)."""

    def __init__(self, python: str):
        self.process = subprocess.Popen(
            [python, str(WORKER)], stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL,
            text=True, bufsize=1,
        )
        line = self.process.stdout.readline().strip()
        if line != "ready":
            self.close()
            raise RuntimeError(f"{python} could not run robosuite's Lift (exit {self.process.returncode})")

    def steps(self, k: int) -> list[float]:
        """Run k env.step calls there; their wall times (ms)."""
        self.process.stdin.write(f"{k}\n")
        return json.loads(self.process.stdout.readline())

    def close(self) -> None:
        if self.process.stdin:
            self.process.stdin.close()
        try:
            self.process.wait(timeout=30)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()


def _start_robosuite() -> RobosuiteLift | None:
    python = robosuite_python()
    if python is None:
        print("  robosuite: no interpreter (TELEOP_ROBOSUITE_PYTHON or .venv-robosuite); figures left out", file=sys.stderr)
        return None
    try:
        return RobosuiteLift(python)
    except (OSError, RuntimeError, ValueError) as exc:
        print(f"  robosuite: {exc}; figures left out", file=sys.stderr)
        return None


def ik_max_diff_vs_mink(n: int, seed: int = 0) -> float:
    """Largest difference (rad/s) between the fast IK and mink.solve_ik over n random reachable targets.

    Half the configurations are anywhere in the joint ranges (the hand often at or in the
    table: collision rows), half near home; targets are the EE pose of a nearby
    configuration, small or large steps (velocity limits active or not).
    """
    import mink

    from teleop.control.ik import SOLVER_DAMPING
    from teleop.control.session import Session

    ik = Session("lift", "panda", seed=0, control_hz=20.0).controller.arms[0].ik
    configuration, site = ik.configuration, ik.arm.ee_site
    rng = np.random.default_rng(seed)
    lo, hi = ik.model.jnt_range[: ik.model.nq].T
    worst = 0.0
    for i in range(n):
        q = rng.uniform(lo, hi) if i % 2 else ik.home + rng.normal(0.0, 0.3, len(lo))
        q = np.clip(q, lo + 0.031, hi - 0.031)
        configuration.update(q + rng.normal(0.0, 0.3 if i % 3 == 0 else 0.03, len(q)))
        ik.frame_task.set_target(configuration.get_transform_frame_to_world(site, "site"))
        configuration.update(q)
        reference = mink.solve_ik(configuration, ik.tasks, ik.dt, "daqp", damping=SOLVER_DAMPING, limits=ik.limits)
        fast = ik.qp.solve()
        worst = max(worst, float(np.max(np.abs(fast - reference))))
    return worst


def tick_parts(session, center: np.ndarray, quat: np.ndarray, n: int) -> dict[str, float]:
    """Each part of a control tick on its own, median us over `n` ticks of the same moving target: the
    command folded into the target (`commands`), the IK solve (`ik`), the joint and gripper ctrl written
    around it (`ctrl`), the physics (`physics`), the poses after it (`poses`), the task judged and its hold
    timed (`judge`: tasks with a `hold`) and the tracking error (`errors`); `measure` adds `rest`: what
    `tick_overhead_us` holds beyond these (events, the observer hooks, the result). A part added to every
    tick shows here."""
    controller = session.controller
    model, data = controller.model, controller.data
    arm = controller.arms[0]
    observe = controller.scene.observer(data)
    scratch = mujoco.MjData(model)
    times: dict[str, list[float]] = {k: [] for k in ("commands", "ik", "ctrl", "physics", "poses", "judge", "errors")}
    clock = time.perf_counter
    for i in range(n):
        command = Command(target_pos=center + _circle(i), target_quat=quat)
        mujoco.mj_copyData(scratch, model, data)
        t0 = clock()
        controller.apply(command)
        t1 = clock()
        arm.ik.solve(arm.target_pos, arm.target_quat)
        t2 = clock()
        scratch.ctrl[arm.ctrl_index] = arm.ik.q
        if arm.gripper_id is not None:
            scratch.ctrl[arm.gripper_id] = arm.ik.arm.gripper.open
        t3 = clock()
        mujoco.mj_step(model, scratch, nstep=session.substeps)
        t4 = clock()
        mujoco.mj_kinematics(model, scratch)
        t5 = clock()
        if observe is not None:
            observe()
        t6 = clock()
        errors = np.array([math.sqrt(float((scratch.site_xpos[a.site_id] - a.target_pos).dot(scratch.site_xpos[a.site_id] - a.target_pos)))
                           for a in controller.arms])
        controller.tracking_errors.append(errors)
        t7 = clock()
        mujoco.mj_copyData(data, model, scratch)  # the scene moves on as a tick would have moved it
        for key, span in zip(times, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6)):
            times[key].append(span * 1e6)
    return {key: round(float(np.median(v)), 1) for key, v in times.items()}


def measure(quick: bool = False) -> dict[str, float]:
    from teleop.control.session import Session

    n = 300 if quick else 2000
    session = Session("lift", "panda", seed=0, control_hz=20.0)
    assert session.substeps == 25 and abs(session.timestep - 0.002) < 1e-12
    arm = session.controller.arms[0]
    center = arm.target_pos.copy()
    quat = arm.target_quat.copy()
    robosuite = _start_robosuite()

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

    # Whole control step. Per tick: the step (its IK solve timed inside), then the bare
    # physics of the same tick on a copy of the state before it under the ctrl it wrote.
    # robosuite's steps run in blocks between ours.
    ik_us: list[float] = []
    solve = arm.ik.solve

    def timed_solve(pos: np.ndarray, q: np.ndarray) -> bool:
        t0 = time.perf_counter()
        ok = solve(pos, q)
        ik_us.append((time.perf_counter() - t0) * 1e6)
        return ok

    arm.ik.solve = timed_solve  # this session only: the instance attribute shadows the method
    scratch = mujoco.MjData(session.controller.model)
    step_ms, physics_ms, overhead_us, robosuite_ms = [], [], [], []
    try:
        for i in range(n):
            if robosuite is not None and i % BLOCK == 0:
                robosuite_ms.extend(robosuite.steps(ROBOSUITE_BLOCK))
            mujoco.mj_copyData(scratch, session.controller.model, session.controller.data)
            command = Command(target_pos=center + _circle(i), target_quat=quat)
            t0 = time.perf_counter()
            session.step([command])
            step = (time.perf_counter() - t0) * 1e3
            scratch.ctrl[:] = session.controller.data.ctrl
            t0 = time.perf_counter()
            mujoco.mj_step(session.controller.model, scratch, nstep=session.substeps)
            physics = (time.perf_counter() - t0) * 1e3
            step_ms.append(step)
            physics_ms.append(physics)
            overhead_us.append((step - physics) * 1e3 - ik_us[-1])
    finally:
        del arm.ik.solve
        if robosuite is not None:
            robosuite.close()
    parts = tick_parts(session, center, quat, 300 if quick else 1500)
    control_step_ms = float(np.median(step_ms))
    physics_step_ms = float(np.median(physics_ms))
    out = {
        "ik_solve_us": round(float(np.median(solve_us)), 1),
        "control_step_ms": round(control_step_ms, 4),
        "physics_step_ms": round(physics_step_ms, 4),
        "control_overhead_x": round(control_step_ms / physics_step_ms, 2),
        "tick_overhead_us": round(float(np.median(overhead_us)), 1),
        "tick_parts_us": {**parts, "rest": round(max(0.0, float(np.median(overhead_us)) - sum(
            v for k, v in parts.items() if k not in ("ik", "physics"))), 1)},
        "control_realtime_factor": round(session.dt * 1e3 / control_step_ms, 1),
    }
    if robosuite_ms:
        out["robosuite_step_ms"] = round(float(np.median(robosuite_ms)), 3)
        out["robosuite_speedup_x"] = round(out["robosuite_step_ms"] / control_step_ms, 1)
    if not quick:
        out["ik_max_diff_vs_mink"] = float(f"{ik_max_diff_vs_mink(IK_CHECKS):.2e}")
    return out
