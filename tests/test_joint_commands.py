"""Joint commands (issue 47 item 1): a leader arm's joint targets drive the simulated arm without IK.

Real MuJoCo sessions: joints reach their targets, are clamped to the joint ranges, the EE target
follows their forward kinematics so keys continue from there, `gripper_opening` sets the gripper's
ctrl, and an episode driven by joint commands records them and replays bit for bit.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from devices.command import Command
from devices.view import SessionView
from replay import load_episode, verify_file
from teleop.control.loop import run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session

pytestmark = pytest.mark.unit

SO101_TARGET = np.array([0.3, -0.4, 0.5, 0.6, 0.2])  # rad, inside every so101 joint's range


@pytest.fixture(scope="module")
def so101() -> Session:
    return Session("lift", "so101", seed=0, control_hz=30.0)


def fresh(session: Session) -> Session:
    session.load(0)
    return session


class JointStream:
    """A device that sends one arm's joint targets (rad) along a smooth path, for `ticks` ticks."""

    kind = "script"

    def __init__(self, start: np.ndarray, end: np.ndarray, ticks: int, opening: bool = True) -> None:
        self.name = "joint-stream"
        self.start_q, self.end_q, self.ticks, self.opening = start, end, ticks, opening
        self.k = 0

    def start(self) -> None:
        self.k = 0

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        if self.k >= self.ticks:
            return []
        s = 0.5 - 0.5 * math.cos(math.pi * self.k / max(1, self.ticks - 1))
        self.k += 1
        q = self.start_q + s * (self.end_q - self.start_q)
        return [Command(joints=q, gripper_opening=1.0 - s if self.opening else None, source=self.name)]

    def status(self) -> str:
        return "done" if self.finished else "running"

    @property
    def finished(self) -> bool:
        return self.k >= self.ticks

    def close(self) -> None:
        pass


def test_the_session_view_describes_the_arms_joints(so101):
    c = fresh(so101).controller
    view: SessionView = c
    assert view.robot_name == "so101" and view.reach == pytest.approx(0.43)
    assert view.joint_names() == ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")
    lo, hi = view.joint_limits()
    assert lo[0] == pytest.approx(-1.91986) and hi[4] == pytest.approx(2.84121)
    assert np.allclose(view.joint_positions(), so101.robot.arms[0].home)
    pos, quat = view.base_pose()
    assert pos.shape == (3,) and np.isclose(np.linalg.norm(quat), 1.0)
    # the base is what the first joint turns about: its position does not move when the arm does
    so101.step([Command(joints=SO101_TARGET)])
    assert np.array_equal(view.joint_targets(), SO101_TARGET)
    assert np.allclose(view.base_pose()[0], pos)


def test_bimanual_joint_names_drop_the_mount_prefix():
    c = Session("lift", "bimanual", seed=0).controller
    assert c.joint_names(0) == c.joint_names(1) == ("waist", "shoulder", "elbow", "forearm_roll", "wrist_angle", "wrist_rotate")
    assert not np.allclose(c.base_pose(0)[0], c.base_pose(1)[0])


def test_joints_drive_the_arm_to_their_targets(so101):
    session = fresh(so101)
    for _ in range(30):  # one second at 30 Hz
        session.step([Command(joints=SO101_TARGET)])
    c = session.controller
    assert np.abs(c.joint_positions() - SO101_TARGET).max() < 0.02
    # held without new commands, and no IK ran to move them elsewhere
    for _ in range(10):
        session.step([])
    assert np.array_equal(c.joint_targets(), SO101_TARGET)


def test_joints_out_of_range_are_clamped_to_the_limits(so101):
    session = fresh(so101)
    lo, hi = session.controller.joint_limits()
    wanted = np.array([5.0, -5.0, 0.1, 9.0, -9.0])
    clamped_before = session.stats.clamped
    session.step([Command(joints=wanted)])
    targets = session.controller.joint_targets()
    assert np.array_equal(targets, [hi[0], lo[1], 0.1, hi[3], lo[4]])
    assert session.stats.clamped == clamped_before + 1


def test_bad_joint_commands_are_ignored_and_counted(so101):
    session = fresh(so101)
    before = session.controller.joint_targets()
    ignored = session.stats.ignored_commands
    session.step([Command(joints=np.array([0.1, 0.2, 0.3]), source="leader")])  # so101 has 5 arm joints
    session.step([Command(joints=np.array([0.1, np.nan, 0.3, 0.0, 0.0]), source="leader")])
    session.step([Command(gripper_opening=math.inf, source="leader")])
    assert session.stats.ignored_commands == ignored + 3
    assert any("ignored joint targets from leader" in m for m in session.stats.messages)
    assert np.abs(session.controller.joint_targets() - before).max() < 0.05  # IK still holds the home pose


def test_the_ee_target_is_the_forward_kinematics_and_keys_continue_from_it(so101):
    session = fresh(so101)
    c = session.controller
    for _ in range(30):
        session.step([Command(joints=SO101_TARGET)])
    target_pos, target_quat = c.target_pose()
    # forward kinematics of the commanded joints, on the arm's own IK model
    ik = c.arms[0].ik
    ik.configuration.update(SO101_TARGET)
    fk = ik.configuration.get_transform_frame_to_world(ik.arm.ee_site, "site")
    assert np.allclose(target_pos, fk.translation(), atol=1e-12)
    assert np.allclose(np.abs(target_quat @ fk.rotation().wxyz), 1.0, atol=1e-12)
    # the simulated EE is there too (it tracked the joints)
    assert np.linalg.norm(c.ee_pose()[0] - target_pos) < 0.01
    # a key delta right after: the target moves by just the delta, and IK drives again from the held joints
    delta = np.array([0.0, 0.005, 0.0])
    session.step([Command(translation=delta)])
    assert np.allclose(c.target_pose()[0], target_pos + delta, atol=1e-12)
    assert c.arms[0].joint_hold is None
    assert np.abs(c.joint_targets() - SO101_TARGET).max() < 0.05  # no jump in the joints either


def test_a_gripper_only_command_keeps_the_joints_held(so101):
    session = fresh(so101)
    session.step([Command(joints=SO101_TARGET)])
    session.step([Command(gripper="close")])
    assert np.array_equal(session.controller.joint_targets(), SO101_TARGET)


@pytest.mark.parametrize("opening, expected", [(0.0, 0.0), (0.5, 0.275), (1.0, 0.55), (1.7, 0.55), (-0.3, 0.0)])
def test_gripper_opening_sets_the_gripper_ctrl_between_closed_and_open(so101, opening, expected):
    session = fresh(so101)
    c = session.controller
    gid = c.arms[0].gripper_id
    session.step([Command(gripper_opening=opening)])
    assert c.data.ctrl[gid] == pytest.approx(expected, abs=1e-12)
    assert c.arms[0].gripper_open is (min(max(opening, 0.0), 1.0) >= 0.5)
    # an open / close command afterwards takes over again
    session.step([Command(gripper="close")])
    assert c.data.ctrl[gid] == 0.0 and c.arms[0].gripper_open is False


def test_a_recorded_joint_episode_replays_bit_for_bit_with_its_joints(so101, tmp_path: Path):
    session = fresh(so101)
    home = np.array(session.robot.arms[0].home)
    device = JointStream(home, SO101_TARGET, ticks=45)
    with Recorder(session, tmp_path, formats=("mcap",), verify="off") as recorder:
        result = run_episode(session, [device])
    assert result.stopped_by == "script_end" and result.steps == 45
    path = recorder.paths[0]
    check = verify_file(path, warn=False)
    assert check.bit_exact is True and check.compared == 44
    episode = load_episode(path)
    sent = [c for step in episode.commands for c in step]
    assert len(sent) == 45 and all(c["source"] == "joint-stream" for c in sent)
    assert sent[0]["joints"] == pytest.approx(home.tolist()) and sent[-1]["joints"] == pytest.approx(SO101_TARGET.tolist())
    assert sent[-1]["gripper_opening"] == pytest.approx(0.0) and sent[0]["gripper_opening"] == 1.0
    # the ctrl recorded is the commanded joints (no IK between), and the EE target their FK
    nj = len(home)
    assert np.array_equal(episode.ctrl[-1, :nj], SO101_TARGET)
    assert np.allclose(episode.ee_target[-1, 0, :3], session.controller.target_pose()[0])


def test_a_panda_episode_driven_by_joint_commands(tmp_path: Path):
    session = Session("lift", "panda", seed=1, control_hz=30.0)
    c = session.controller
    assert len(c.joint_names()) == 7
    home = c.joint_positions()
    goal = home + np.array([0.3, 0.2, -0.2, -0.3, 0.2, 0.3, -0.4])
    with Recorder(session, tmp_path, formats=("mcap",), verify="sync") as recorder:
        result = run_episode(session, [JointStream(home, goal, ticks=30, opening=False)])
        for _ in range(15):
            session.step([])
    assert result.steps == 30 and recorder.last_verify is not None and recorder.last_verify.bit_exact
    assert np.abs(c.joint_positions() - goal).max() < 0.02
    episode = load_episode(recorder.paths[0])
    assert len(episode.commands[0][0]["joints"]) == 7


def test_a_joint_command_is_not_idle_and_its_dict_is_json():
    assert Command().is_idle()
    assert not Command(joints=np.zeros(5)).is_idle() and not Command(gripper_opening=0.0).is_idle()
    d = Command(joints=np.array([0.1, -0.2]), gripper_opening=0.25).to_dict()
    assert d["joints"] == [0.1, -0.2] and d["gripper_opening"] == 0.25
    assert Command().to_dict()["joints"] is None and Command().to_dict()["gripper_opening"] is None
