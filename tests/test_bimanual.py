"""Bimanual: each arm follows its own commands and the other holds still."""

from __future__ import annotations

import numpy as np
import pytest

from devices.command import Command
from teleop.control.session import Session


@pytest.mark.parametrize("moving", [0, 1])
def test_arms_move_independently(moving):
    session = Session("handover", "bimanual", seed=0)
    assert session.controller.n_arms == 2
    still = 1 - moving
    start = [session.controller.ee_pose(i)[0] for i in range(2)]
    for _ in range(30):  # 1 s at 30 Hz, 5 cm up and 3 cm sideways
        session.step([Command(translation=np.array([0.0, 0.001, 0.05 / 30]), arm=moving)])
    moved = session.controller.ee_pose(moving)[0] - start[moving]
    held = session.controller.ee_pose(still)[0] - start[still]
    assert moved[2] > 0.045 and moved[1] > 0.025
    assert np.linalg.norm(held) < 0.001
    # Grippers are independent too.
    for _ in range(10):
        session.step([Command(gripper="close", arm=moving)])
    assert session.controller.arms[moving].gripper_open is False and session.controller.arms[still].gripper_open is True


def test_commands_for_a_missing_arm_are_ignored():
    session = Session("lift", "panda", seed=0)
    session.step([Command(translation=np.array([0.01, 0, 0]), arm=1)])
    assert session.stats.ignored_commands == 1


def test_bimanual_cameras_and_names():
    session = Session("lift", "bimanual", seed=0)
    assert {"front", "overhead", "left/wrist", "right/wrist"} <= set(session.scene.cameras)
    assert [a.ee_site for a in session.scene.arms] == ["left/ee_site", "right/ee_site"]
