"""The fast IK (teleop.control.ik_qp.ArmQP) solves mink's own problem: same velocity as mink.solve_ik."""

from __future__ import annotations

import mink
import numpy as np
import pytest

from scenes import BUILTIN_ROBOTS, load_robot
from teleop.control.ik import SOLVER_DAMPING, ArmIK
from teleop.control.session import Session

TOLERANCE = 1e-9  # rad/s


def _compare(ik: ArmIK, n: int, seed: int) -> dict[str, int]:
    """Random reachable targets from random configurations: fast vs mink.solve_ik, and what was active."""
    configuration, site = ik.configuration, ik.arm.ee_site
    rng = np.random.default_rng(seed)
    lo, hi = ik.model.jnt_range[: ik.model.nq].T
    collision = [limit for limit in ik.limits if isinstance(limit, mink.CollisionAvoidanceLimit)]
    seen = {"box_active": 0, "none_active": 0, "collision_rows": 0}
    for i in range(n):
        # Anywhere in the joint ranges (the hand often at or in the table) or near home.
        q = rng.uniform(lo, hi) if i % 2 else ik.home + rng.normal(0.0, 0.3, len(lo))
        q = np.clip(q, lo + 0.031, hi - 0.031)
        # The target is where a nearby configuration puts the EE: reachable; big steps hit the velocity limits.
        configuration.update(q + rng.normal(0.0, 0.3 if i % 3 == 0 else 0.03, len(q)))
        ik.frame_task.set_target(configuration.get_transform_frame_to_world(site, "site"))
        configuration.update(q)
        reference = mink.solve_ik(configuration, ik.tasks, ik.dt, "daqp", damping=SOLVER_DAMPING, limits=ik.limits)
        fast = ik.qp.solve()
        assert fast is not None and np.max(np.abs(fast - reference)) <= TOLERANCE, (i, fast, reference)
        dq = fast * ik.dt
        on_box = np.isclose(dq, ik.qp.upper, atol=1e-12) | np.isclose(dq, ik.qp.lower, atol=1e-12)
        seen["box_active" if on_box.any() else "none_active"] += 1
        for limit in collision:
            if np.any(np.isfinite(limit.compute_qp_inequalities(configuration, ik.dt).h)):
                seen["collision_rows"] += 1
                # The filter that skips the table rows must never skip a pair mink would constrain.
                assert any(near.any_near() for _, near in ik.qp.collisions), i
    return seen


@pytest.mark.e2e  # 10,000 solves each way: seconds; every built-in arm is compared in the quick suite below
def test_fast_ik_matches_mink_on_10000_targets():
    ik = Session("lift", "panda", seed=0, control_hz=20.0).controller.arms[0].ik
    assert ik.qp is not None, "the Panda takes the fast path"
    seen = _compare(ik, 10_000, seed=0)
    # Both regimes were exercised: limits binding and free, and the table rows present.
    assert seen["box_active"] > 1000 and seen["none_active"] > 1000 and seen["collision_rows"] > 100, seen


@pytest.mark.parametrize("robot", [r for r in BUILTIN_ROBOTS if r != "panda"])
def test_fast_ik_matches_mink_for_every_builtin_arm(robot):
    spec = load_robot(robot)
    session = Session("handover" if spec.bimanual else "lift", robot, seed=0, control_hz=20.0)
    for i, arm in enumerate(session.controller.arms):
        assert arm.ik.qp is not None
        _compare(arm.ik, 300, seed=i)


def test_ik_steps_match_mink_through_arm_ik():
    """Whole solves (acceleration bound, integration, range clip) along a path: same joints as with mink."""
    fast = Session("lift", "panda", seed=0, control_hz=30.0).controller.arms[0].ik
    reference = Session("lift", "panda", seed=0, control_hz=30.0).controller.arms[0].ik
    reference.qp = None  # mink.solve_ik path
    pos, quat = fast.ee_pose()
    for i in range(300):
        a = 0.05 * i
        target = pos + np.array([0.15 * np.cos(a) - 0.15, 0.15 * np.sin(a), -0.25 * np.sin(a / 3) ** 2])
        assert fast.solve(target, quat) == reference.solve(target, quat)
        assert np.max(np.abs(fast.q - reference.q)) < 1e-9, i
