"""Bring your own robot: a TOML + MJCF (with a mesh and motor actuators) written here, end to end."""

from __future__ import annotations

import json
import textwrap
from pathlib import Path

import numpy as np
import pytest

from scenes import SceneError, load_robot
from teleop.control.session import Session
from tests.conftest import assert_one_line_error, run_cli, run_json

# A 6-DoF arm unlike the built-ins: an elbow-up anthropomorphic arm driven by
# motors (the loader must replace them with position actuators), a mesh base
# loaded from the model's own folder, and a two-finger gripper.
ARM_XML = """
<mujoco model="test_arm">
  <compiler angle="radian" meshdir="meshes"/>
  <asset><mesh name="base_mesh" file="base.obj"/></asset>
  <worldbody>
    <body name="base">
      <geom type="mesh" mesh="base_mesh" rgba="0.3 0.3 0.35 1"/>
      <body name="l1" pos="0 0 0.12">
        <joint name="j1" axis="0 0 1" range="-3 3" armature="0.05" damping="1"/>
        <geom type="cylinder" pos="0 0 0.03" size="0.05 0.025" mass="2"/>
        <body name="l2" pos="0 0 0.06">
          <joint name="j2" axis="0 1 0" range="-2 2" armature="0.05" damping="1"/>
          <geom type="capsule" fromto="0 0 0 0 0 0.3" size="0.04" mass="2"/>
          <body name="l3" pos="0 0 0.3">
            <joint name="j3" axis="0 1 0" range="-2.5 2.5" armature="0.05" damping="1"/>
            <geom type="capsule" fromto="0 0 0 0.28 0 0" size="0.035" mass="1.2"/>
            <body name="l4" pos="0.28 0 0">
              <joint name="j4" axis="1 0 0" range="-3 3" armature="0.02" damping="0.5"/>
              <geom type="capsule" fromto="0 0 0 0.05 0 0" size="0.03" mass="0.4"/>
              <body name="l5" pos="0.05 0 0">
                <joint name="j5" axis="0 1 0" range="-2 2" armature="0.02" damping="0.5"/>
                <geom type="capsule" fromto="0 0 0 0.05 0 0" size="0.03" mass="0.3"/>
                <body name="l6" pos="0.05 0 0">
                  <joint name="j6" axis="1 0 0" range="-3 3" armature="0.02" damping="0.5"/>
                  <geom type="box" pos="0.015 0 0" size="0.015 0.05 0.02" mass="0.3"/>
                  <site name="tool_center" pos="0.075 0 0" size="0.005"/>
                  <body name="fa" pos="0.03 0 0">
                    <joint name="fa" type="slide" axis="0 1 0" range="0 0.035" damping="2"/>
                    <geom type="box" pos="0.045 0.006 0" size="0.035 0.005 0.01" mass="0.02" friction="1.5" condim="4"/>
                  </body>
                  <body name="fb" pos="0.03 0 0">
                    <joint name="fb" type="slide" axis="0 -1 0" range="0 0.035" damping="2"/>
                    <geom type="box" pos="0.045 -0.006 0" size="0.035 0.005 0.01" mass="0.02" friction="1.5" condim="4"/>
                  </body>
                </body>
              </body>
            </body>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
  <tendon><fixed name="grip"><joint joint="fa" coef="0.5"/><joint joint="fb" coef="0.5"/></fixed></tendon>
  <equality><joint joint1="fa" joint2="fb"/></equality>
  <actuator>
    <motor name="m1" joint="j1" gear="1"/>
    <motor name="m2" joint="j2" gear="1"/>
    <position name="fingers" tendon="grip" kp="300" ctrlrange="0 0.035"/>
  </actuator>
  <keyframe><key name="ready" qpos="0 0 0.3 0 1.27 0 0.035 0.035"/></keyframe>
</mujoco>
"""

CUBE_OBJ = "\n".join(
    [f"v {x} {y} {z}" for x in (-0.07, 0.07) for y in (-0.07, 0.07) for z in (0.0, 0.12)]
    + ["f 1 2 4 3", "f 5 7 8 6", "f 1 5 6 2", "f 3 4 8 7", "f 1 3 7 5", "f 2 6 8 4"]
)


def make_robot(folder: Path, toml_body: str | None = None) -> Path:
    (folder / "meshes").mkdir(parents=True, exist_ok=True)
    (folder / "meshes" / "base.obj").write_text(CUBE_OBJ)
    (folder / "test_arm.xml").write_text(ARM_XML)
    toml = folder / "test_arm.toml"
    toml.write_text(toml_body if toml_body is not None else textwrap.dedent("""
        name = "test_arm"
        mjcf = "test_arm.xml"
        ee_site = "tool_center"
        joints = ["j1", "j2", "j3", "j4", "j5", "j6"]
        home = "ready"
        orientation_cost = 0.5
        kp = 2500
        [gripper]
        actuator = "fingers"
        open = 0.035
        closed = 0.0
    """))
    return toml


def test_user_robot_runs_end_to_end(tmp_path):
    toml = make_robot(tmp_path / "robot")
    robot = load_robot(toml)
    session = Session("lift", robot, seed=0)
    model = session.model
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
        assert np.all(np.isfinite(session.data.qpos))
        q = session.data.qpos[[session.model.joint(f"j{i}").qposadr[0] for i in range(1, 7)]]
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


@pytest.mark.parametrize("case", list(BAD))
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
