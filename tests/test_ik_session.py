"""IK and the control loop: tracking, joint limits, unreachable and NaN targets, rates."""

from __future__ import annotations

import numpy as np
import pytest

from devices.script import ScriptDevice
from scenes import BUILTIN_ROBOTS, load_robot
from devices.command import Command
from teleop.control.controller import physics_split
from teleop.control.session import Session

from tests.support import write_script


def _run(session: Session, device: ScriptDevice) -> None:
    while not device.finished:
        session.step(device.poll(session.controller, session.dt))


def _reach_steps(reach: float) -> list[dict]:
    """A free-space square at 0.25 m/s, sized to the robot."""
    d = round(0.12 * reach / 0.85, 3)
    t = d / 0.25
    return [
        {"duration": 0.3},
        {"duration": t, "move": [0, d, 0]},
        {"duration": t, "move": [0, 0, -d]},
        {"duration": t, "move": [0, -d, 0]},
        {"duration": t, "move": [0, 0, d]},
    ]


@pytest.mark.parametrize("robot", list(BUILTIN_ROBOTS))
def test_scripted_reach_tracks_within_two_mm(robot, tmp_path):
    spec = load_robot(robot)
    session = Session("handover" if spec.bimanual else "lift", robot, seed=0)
    device = ScriptDevice(write_script(tmp_path / "reach.json", _reach_steps(spec.reach)))
    device.start()
    start = session.controller.ee_pose(0)[0]
    _run(session, device)
    errors = np.concatenate(session.controller.tracking_errors) * 1000
    assert np.median(errors) <= 2.0, f"median {np.median(errors):.2f} mm"
    assert np.max(errors) <= 10.0, f"max {np.max(errors):.2f} mm"
    assert session.stats.ik_failures == 0
    # It really moved (a square that returns home), and came back.
    assert np.linalg.norm(session.controller.ee_pose(0)[0] - start) < 0.01


def test_joint_limits_are_never_exceeded():
    session = Session("lift", "panda", seed=0)
    model = session.controller.model
    joints = [model.joint(j) for j in session.scene.arms[0].joints]
    far = [np.array(p) for p in ([0.9, 0.6, 0.9], [-0.5, -0.7, 0.1], [0.2, 0.0, 1.5], [0.8, -0.8, 0.1])]
    for target in far:
        for _ in range(60):
            session.step([Command(target_pos=target, rotation=np.array([0.0, 0.0, 0.2]))])
            for j in joints:
                q = session.controller.data.qpos[j.qposadr[0]]
                lo, hi = j.range
                assert lo - 1e-3 <= q <= hi + 1e-3, (j.name, q, lo, hi)
            assert np.all(session.controller.arms[0].ik.q >= model.jnt_range[[j.id for j in joints], 0] - 1e-9)


def test_unreachable_and_nan_targets_are_survived():
    session = Session("lift", "panda", seed=0)
    for _ in range(60):
        session.step([Command(target_pos=np.array([10.0, 10.0, 10.0]))])
    assert session.stats.clamped > 0
    assert np.all(np.isfinite(session.controller.data.qpos))
    assert np.max(np.abs(session.controller.data.qvel)) < 5.0, "the arm must not explode"
    pos_before = session.controller.ee_pose(0)[0]
    target_before = session.controller.target_pose(0)[0]
    for bad in (np.array([np.nan, 0.0, 0.5]), np.array([np.inf, 0, 0])):
        session.step([Command(target_pos=bad)])
        session.step([Command(translation=np.array([np.nan, 0, 0]))])
        session.step([Command(target_quat=np.array([np.nan, 0, 0, 1.0]))])
    assert session.stats.ignored_commands == 6
    assert np.all(np.isfinite(session.controller.data.qpos))
    assert np.array_equal(session.controller.target_pose(0)[0], target_before)
    assert np.linalg.norm(session.controller.ee_pose(0)[0] - pos_before) < 0.05
    assert any("non-finite" in m for m in session.stats.messages)


def test_ik_failure_holds_last_good_solution():
    session = Session("lift", "panda", seed=0)
    arm = session.controller.arms[0]
    q_before = arm.ik.q.copy()
    ok = arm.ik.solve(np.array([np.nan, 0.0, 0.0]), np.array([1.0, 0, 0, 0]))
    assert not ok
    assert np.array_equal(arm.ik.q, q_before)


@pytest.mark.parametrize("hz,substeps", [(30, 17), (20, 25), (50, 10), (500, 1)])
def test_control_rate_is_exact(hz, substeps):
    n, dt = physics_split(hz)
    assert n == substeps and dt <= 0.002 + 1e-12
    assert n * dt == pytest.approx(1 / hz, rel=1e-12)


def test_gripper_follows_open_close_commands():
    session = Session("lift", "panda", seed=0)
    fingers = session.controller.model.joint("finger_joint1").qposadr[0]
    for _ in range(20):
        session.step([Command(gripper="close")])
    closed = session.controller.data.qpos[fingers]
    for _ in range(20):
        session.step([Command(gripper="open")])
    opened = session.controller.data.qpos[fingers]
    assert closed < 0.005 and opened > 0.035
    session.step([Command(gripper="toggle")])
    assert session.controller.arms[0].gripper_open is False


def test_world_and_ee_frame_deltas():
    session = Session("lift", "panda", seed=0)
    p0, q0 = session.controller.target_pose(0)
    session.step([Command(translation=np.array([0.0, 0.0, 0.01]), frame="world")])
    assert np.allclose(session.controller.target_pose(0)[0] - p0, [0, 0, 0.01])
    # The Panda's hand points down at home: +z in the EE frame is world -z.
    session.step([Command(translation=np.array([0.0, 0.0, 0.01]), frame="ee")])
    assert np.allclose(session.controller.target_pose(0)[0] - p0, [0, 0, 0.0], atol=1e-3)


@pytest.mark.parametrize("scene", ["lift", "stack"])
def test_success_is_judged_once_a_tick(scene):
    """A task with a `hold` (lift) is judged by the step, one without (stack) on the first ask: either way the
    page's snapshot asking again in the same tick does not judge twice, and the answer is the predicate's."""
    session = Session(scene=scene)
    c = session.controller
    task = c.scene.task
    judge = task.success
    calls: list[float] = []
    task.success = lambda model, data: (calls.append(data.time), judge(model, data))[1]
    observe = c._observe  # the step's own judge of a task with a `hold`, bound once (None without one)
    if observe is not None:
        c._observe = lambda: (calls.append(c.data.time), observe())[1]
    assert (observe is not None) == (task.hold > 0)
    for tick in range(1, 4):
        before = len(calls)
        c.step([Command(translation=np.array([0.0, 0.0, 0.002]))])
        first, again = c.success(), c.success()
        assert len(calls) - before == 1, f"tick {tick}: judged {len(calls) - before} times"
        assert first == again == judge(c.model, c.data)
    c.data.time += c.dt  # the state changed outside a step: judged afresh
    c.success()
    assert len(calls) == 4
