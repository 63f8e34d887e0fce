"""Perception from a rendered RGB-D view (issue 59, item 1): objects found by colour, back-projected to world
positions within a centimetre of the truth, occlusion by the arm reported, and `teleop perceive`."""

from __future__ import annotations

import json
import math

import mujoco
import numpy as np
import pytest

from devices.script import ScriptDevice, heading
from teleop.control.loop import run_episode
from teleop.control.session import Session
from teleop.instruct.compare import compared
from teleop.instruct.perceive import RgbdCamera, back_project, rectangle
from tests.support import assert_one_line_error, run_cli, write_script

SEEDS = range(20)


@pytest.fixture(scope="module")
def rgbd():
    session = Session(scene="lift", robot="panda", seed=0, control_hz=30)
    camera = RgbdCamera(session.controller.model, 224, 224)
    yield camera
    camera.close()
    session.close()


@pytest.mark.parametrize("scene", ["lift", "stack", "pick_place"])
def test_every_object_in_view_is_found_within_a_centimetre(scene, rgbd):
    session = Session(scene=scene, robot="panda", seed=0, control_hz=30)
    rows, yaw_errors = [], []
    for seed in SEEDS:
        session.reset(seed)
        c = session.controller
        rgbd.load(c.model)
        _, found = compared(c, rgbd=rgbd)
        rows += found
        for r in found:
            if r["yaw"] is not None and r["visible"]:
                true_yaw = heading(c.body_quat(r["name"]))
                d = (r["yaw"] - true_yaw + math.pi / 4) % (math.pi / 2) - math.pi / 4  # a cube's yaw is known mod pi/2
                yaw_errors.append(abs(d))
    session.close()
    visible = [r for r in rows if r["visible"]]
    assert len(visible) >= 0.9 * len(rows), [(r["name"], r["status"]) for r in rows if not r["visible"]]
    worst = max(visible, key=lambda r: r["error_m"])
    assert worst["error_m"] < 0.01, worst
    assert all(r["estimated"][2] == pytest.approx(r["true"][2], abs=0.01) for r in visible)
    if yaw_errors:
        assert max(yaw_errors) < math.radians(10)


@pytest.mark.unit
def test_an_object_behind_the_arm_is_reported_occluded(tmp_path, rgbd):
    session = Session(scene="lift", robot="panda", seed=0, control_hz=30)
    c = session.controller
    cube = c.body_pos("cube")
    eye = c.data.cam_xpos[mujoco.mj_name2id(c.model, mujoco.mjtObj.mjOBJ_CAMERA, "front")]
    between = cube + 0.1 * (eye - cube) / np.linalg.norm(eye - cube)  # the hand 10 cm from the cube, toward the camera
    script = write_script(tmp_path / "hide.json", [{"duration": 2.0, "to": [float(v) for v in between]}])
    rgbd.load(c.model)
    _, before = compared(c, rgbd=rgbd)
    run_episode(session, [ScriptDevice(script)])
    _, after = compared(session.controller, rgbd=rgbd)
    session.close()
    assert before[0]["visible"] and before[0]["occluded_fraction"] == 0.0
    assert not after[0]["visible"] and after[0]["status"] == "occluded", after[0]
    assert after[0]["pixels"] < before[0]["pixels"]


@pytest.mark.unit
def test_back_projection_puts_the_table_at_its_height(rgbd):
    """The pinhole model and the camera's pose: the table's pixels land on z = 0 wherever they are in the image."""
    session = Session(scene="lift", robot="panda", seed=0, control_hz=30)
    c = session.controller
    rgbd.load(c.model)
    mujoco.mj_forward(c.model, c.data)
    _, depth = rgbd.capture(c.data, "front")
    points = back_project(depth, c.model, c.data, rgbd.camera_id("front"))
    session.close()
    centre = points[100:140, 60:170, 2]  # the table top in front's view (no object there at seed 0)
    assert np.median(np.abs(centre)) < 0.002


@pytest.mark.unit
def test_a_rotated_rectangle_gives_its_yaw():
    rng = np.random.default_rng(0)
    pts = rng.uniform([-0.03, -0.01], [0.03, 0.01], size=(400, 2))
    a = 0.5
    rot = np.array([[math.cos(a), -math.sin(a)], [math.sin(a), math.cos(a)]])
    yaw, half = rectangle(pts @ rot.T)
    assert yaw == pytest.approx(a, abs=math.radians(2)) and half == pytest.approx(0.03, abs=0.003)


def test_perceive_prints_estimate_truth_and_error(tmp_path):
    image = tmp_path / "seen.png"
    result = run_cli("perceive", "--scene", "stack", "--seed", "2", "--image", str(image), "--json")
    assert result.returncode == 0, result.stderr[-2000:]
    out = json.loads(result.stdout)
    assert out["camera"] == "front" and image.is_file() and image.stat().st_size > 1000
    assert [o["name"] for o in out["objects"]] == ["cube", "cube_base"]
    for o in out["objects"]:
        assert {"name", "estimated", "true", "error_m", "visible"} <= set(o)
        assert o["visible"] and o["error_m"] < 0.01
        assert o["error_m"] == pytest.approx(float(np.linalg.norm(np.subtract(o["estimated"], o["true"]))), abs=2e-4)
    bad = run_cli("perceive", "--scene", "stack", "--camera", "nowhere", "--image", str(image))
    assert_one_line_error(bad, "nowhere", "front")
