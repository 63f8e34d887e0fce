"""Bring your own robot: a TOML + MJCF (with a mesh and motor actuators) written here, end to end."""

from __future__ import annotations

import json
import textwrap

import numpy as np
import pytest

from scenes import SceneError, load_robot
from teleop.control.session import Session
from tests.support import assert_one_line_error, make_robot, run_cli, run_json

def test_user_robot_runs_end_to_end(tmp_path):
    toml = make_robot(tmp_path / "robot")
    robot = load_robot(toml)
    session = Session("lift", robot, seed=0)
    model = session.controller.model
    # Motors were replaced by position actuators, one per arm joint.
    names = [model.actuator(i).name for i in range(model.nu)]
    assert "m1" not in names and "m2" not in names
    assert {f"j{i}_position" for i in range(1, 7)} <= set(names)
    assert model.nmesh == 1  # the mesh came from the model's own folder
    script = tmp_path / "reach.json"
    script.write_text(json.dumps({"steps": [
        {"duration": 0.4, "move": [0, 0.08, 0]},
        {"duration": 0.4, "move": [0, 0, -0.08], "gripper": "close"},
        {"duration": 0.4, "move": [0, -0.08, 0.08], "gripper": "open"},
    ]}))
    out = run_json("run", "--robot", str(toml), "--device", f"script:{script}", "--json")
    assert out["robot"] == "test_arm"
    assert out["ik_failures"] == 0
    assert out["ee_tracking_error_mm"]["median"] < 5.0
    assert out["steps"] == 36


def test_user_robot_home_as_list_and_other_scenes(tmp_path):
    toml = make_robot(tmp_path / "robot", textwrap.dedent("""
        name = "test_arm"
        mjcf = "test_arm.xml"
        ee_site = "tool_center"
        joints = ["j1", "j2", "j3", "j4", "j5", "j6"]
        home = [0.0, 0.0, 0.3, 0.0, 1.27, 0.0]
    """))
    for scene in ("stack", "door", "pick_place"):
        session = Session(scene, load_robot(toml), seed=1)
        for _ in range(30):
            session.step([])
        assert np.all(np.isfinite(session.controller.data.qpos))
        q = session.controller.data.qpos[[session.controller.model.joint(f"j{i}").qposadr[0] for i in range(1, 7)]]
        assert np.allclose(q, [0.0, 0.0, 0.3, 0.0, 1.27, 0.0], atol=0.05)


BAD = {
    "missing": ('name = "x"\nmjcf = "test_arm.xml"\njoints = ["j1"]\n', "missing required field 'ee_site'"),
    "site": ('name = "x"\nmjcf = "test_arm.xml"\nee_site = "nope"\njoints = ["j1"]\nhome = [0.0]\n', "ee_site 'nope'"),
    "joint": ('name = "x"\nmjcf = "test_arm.xml"\nee_site = "tool_center"\njoints = ["j1", "j9"]\nhome = [0.0, 0.0]\n', "joint 'j9'"),
    "home": ('name = "x"\nmjcf = "test_arm.xml"\nee_site = "tool_center"\njoints = ["j1"]\nhome = [0.0, 1.0]\n', "'home'"),
    "toml": ('name = "x\nmjcf = ', "not valid TOML"),
    "mjcf_missing": ('name = "x"\nmjcf = "gone.xml"\nee_site = "s"\njoints = ["j1"]\n', "not found"),
    "gripper": ('name = "x"\nmjcf = "test_arm.xml"\nee_site = "tool_center"\njoints = ["j1"]\nhome = [0.0]\n'
                '[gripper]\nactuator = "claw"\nopen = 1\nclosed = 0\n', "gripper actuator 'claw'"),
}


# A fresh `teleop run` each: the first case runs in the quick suite, the others in e2e.
@pytest.mark.parametrize("case", [pytest.param(c, marks=() if c == "missing" else pytest.mark.e2e) for c in BAD])
def test_bad_robot_files_give_one_line(tmp_path, case):
    body, needle = BAD[case]
    toml = make_robot(tmp_path / "robot", body)
    script = tmp_path / "s.json"
    script.write_text('{"steps": [{"duration": 0.1}]}')
    assert_one_line_error(run_cli("run", "--robot", str(toml), "--device", f"script:{script}"), needle)


def test_mjcf_that_does_not_compile(tmp_path):
    toml = make_robot(tmp_path / "robot")
    (tmp_path / "robot" / "test_arm.xml").write_text("<mujoco><worldbody><body><geom type='sphere'/></body></worldbody")
    with pytest.raises(SceneError, match="MJCF does not load"):
        Session("lift", load_robot(toml))
