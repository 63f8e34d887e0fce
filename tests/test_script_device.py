"""The script device (issue 38 items 4 and 7): a whole script is checked against the scene before
the first tick, and a step can set an absolute hand orientation or turn the hand to an object's yaw."""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest

import teleop
from devices.script import ScriptDevice, ScriptError, heading, parse_script
from teleop.control.recording import Recorder
from tests.support import write_script


def _session(scene: str = "lift", seed: int = 0) -> teleop.Session:
    return teleop.Session(scene=scene, robot="panda", seed=seed, control_hz=30)


@pytest.mark.parametrize("bad,needles", [
    ({"duration": 0.1, "to_body": "cubee"}, ["step 5", "'to_body'", "cubee"]),
    ({"duration": 0.1, "move": [0, 0, 0.01], "arm": 1}, ["step 5", "'arm' 1", "1 arm(s)"]),
])
def test_a_bad_name_in_step_5_stops_the_run_before_the_first_tick_and_records_nothing(bad, needles, tmp_path):
    steps = [{"duration": 0.1, "move": [0, 0, 0.01]}] * 4 + [bad]
    script = write_script(tmp_path / "script.json", steps)
    session = _session()
    Recorder(session, tmp_path / "episodes", ("mcap",))
    with pytest.raises(ScriptError) as caught:
        teleop.run_episode(session, [ScriptDevice(script)])
    message = str(caught.value)
    assert "\n" not in message and str(script) in message
    for needle in needles:
        assert needle in message, message
    assert session.controller.time == 0.0  # not one tick ran
    assert not session.recorder.recording
    assert session.close() == []  # closing saves nothing: no episode was begun
    assert not list((tmp_path / "episodes").glob("*")) if (tmp_path / "episodes").exists() else True


@pytest.mark.parametrize("step,needle", [
    ({"duration": 1, "align": "yaw"}, "'align' needs 'to_body'"),
    ({"duration": 1, "to_body": "cube", "align": "roll"}, "'align' must be \"yaw\""),
    ({"duration": 1, "orient": [0, 0]}, "'orient' must be a list of 3 finite numbers"),
    ({"duration": 1, "rotate": [0, 0, 1], "orient": [3.14, 0, 0]}, "'orient' cannot be combined with 'rotate'"),
    ({"duration": 1, "to_body": "cube", "orient": [3.14, 0, 0], "align": "yaw"}, "'align' cannot be combined with 'orient'"),
])
def test_orient_and_align_are_checked_when_read(step, needle):
    with pytest.raises(ScriptError, match="step 1") as caught:
        parse_script(json.dumps({"steps": [step]}))
    assert needle in str(caught.value)


def _hand_down_and_heading(quat: np.ndarray) -> tuple[float, float]:
    """(z of the hand's z axis: -1 pointing straight down, the hand's heading in rad)."""
    mat = np.empty(9)
    mujoco.mju_quat2Mat(mat, quat)
    return float(mat[8]), heading(quat)


def test_orient_sets_the_hand_orientation_whatever_it_was(tmp_path):
    """An absolute [roll, pitch, yaw]: after an arbitrary relative turn, `orient` lands on the same pose."""
    script = write_script(tmp_path / "orient.json", [
        {"duration": 0.3, "rotate": [0, 0, -0.9]},
        {"duration": 0.5, "orient": [math.pi, 0, 0.6]},
    ])
    session = _session()
    start_down, start_heading = _hand_down_and_heading(session.controller.target_pose(0)[1])
    assert start_down < -0.999 and abs(start_heading) < 1e-3  # every built-in hand starts at [pi, 0, 0]
    teleop.run_episode(session, [ScriptDevice(script)])
    down, turned = _hand_down_and_heading(session.controller.target_pose(0)[1])
    assert down < -0.999 and turned == pytest.approx(0.6, abs=1e-6)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_align_turns_the_hand_to_the_objects_yaw_by_the_nearer_grasp(seed, tmp_path):
    """lift_l_block places its L at any yaw; `align` gives the hand that yaw mod pi, turning at most pi/2."""
    script = write_script(tmp_path / "align.json", [
        {"duration": 0.5, "to_body": "l_block", "offset": [0, 0, 0.12], "align": "yaw"},
    ])
    session = _session("lift_l_block", seed)
    block = heading(session.controller.body_quat("l_block"))
    before = heading(session.controller.target_pose(0)[1])
    teleop.run_episode(session, [ScriptDevice(script)])
    down, hand = _hand_down_and_heading(session.controller.target_pose(0)[1])
    assert down < -0.999
    assert math.sin(hand - block) == pytest.approx(0.0, abs=1e-6)  # the same line: yaw or yaw + pi
    assert abs(math.remainder(hand - before, 2 * math.pi)) <= math.pi / 2 + 1e-9  # the nearer of the two
