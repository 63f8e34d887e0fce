"""Grasps: a lift counts only when the object is held, and a gripper closing on an edge pushes, never throws.

The near-miss measurement is bench/grasp.py; here `teleop bench --only grasp --quick` runs it at a few seeds.
"""

from __future__ import annotations

import re

import tomllib

import mujoco
import pytest

from scenes.assembly.build import build_scene
from scenes.tasks.file_task import task_from_bundle
from scenes.tasks.expr import And, Pred, parse
from scenes.tasks.registry import BUILTIN_DIR, find_task, library_tasks
from tests.support import run_json

HAND_SPEED = 0.5  # m/s: the bound on a pushed object's speed, a person's hand
OLD_LIFT = 'success = "lifted(cube, 0.05)"'  # lift.toml's success before lifts needed a grasp
NEW_LIFT = 'success = "grasped(cube) and lifted(cube, 0.05)"'


def _cube_in_the_air(robot: str) -> tuple:
    """The lift scene with the cube 10 cm over where it started, touching nothing: thrown, not held."""
    scene = build_scene("lift", robot, seed=0)
    data = scene.make_data()
    adr = scene.model.jnt_qposadr[scene.model.body_jntadr[scene.model.body("cube").id]]
    data.qpos[adr + 2] += 0.10
    mujoco.mj_forward(scene.model, data)
    return scene, data


@pytest.mark.parametrize("robot", ["panda", "so101"])
def test_a_cube_in_the_air_but_not_held_is_no_lift(robot, tmp_path, monkeypatch):
    monkeypatch.setenv("TELEOP_CACHE", str(tmp_path))
    scene, data = _cube_in_the_air(robot)
    assert data.ncon == 0 or all(scene.model.body("cube").id not in
                                 (scene.model.geom_bodyid[c.geom1], scene.model.geom_bodyid[c.geom2]) for c in data.contact[:data.ncon])
    assert scene.task.success(scene.model, data) is False
    # An episode recorded before lifts needed a grasp embeds its task file: judged by it, the verdict stays.
    bundle = find_task("lift").bundle()
    assert NEW_LIFT in bundle["toml"]
    old_toml = re.sub(r"\nhold = [^\n]*", "", bundle["toml"].replace(NEW_LIFT, OLD_LIFT))  # nor a hold time then
    assert old_toml != bundle["toml"] and "hold" not in old_toml.split("[[object]]")[0]
    old = task_from_bundle({**bundle, "toml": old_toml})
    assert old.success(scene.model, data) is True


def test_every_lift_task_needs_a_grasp():
    """The built-in lift and the library's lift family: grasped(x) and lifted(x, h), the same x (files read, not built)."""
    files = [BUILTIN_DIR / "lift.toml", *library_tasks().values()]
    lifts = [raw for raw in (tomllib.loads(f.read_text()) for f in files) if raw.get("family") == "lift"]
    assert len(lifts) >= 6
    for raw in lifts:
        expr = parse(raw["success"])
        assert isinstance(expr, And), raw["name"]
        held = {p.name: p.args[0] for p in expr.args if isinstance(p, Pred)}
        assert held.get("grasped") is not None and held.get("grasped") == held.get("lifted"), (raw["name"], expr)
        assert raw.get("hold", 0) > 0, f"{raw['name']}: held and lifted for a hold time, not for one tick"


@pytest.mark.e2e
def test_a_gripper_closing_on_the_cube_edge_pushes_it_no_faster_than_a_hand():
    """`teleop bench --only grasp --quick`: 4 scripted near misses a robot, the gripper closing on the cube's edge."""
    out = run_json("bench", "--only", "grasp", "--quick", "--json")
    per_robot = {k: v for k, v in out.items() if k.startswith("grasp_edge_max_speed_")}
    assert set(per_robot) == {f"grasp_edge_max_speed_{r}" for r in ("panda", "ur5e", "so101", "bimanual")}
    assert all(v > 0.005 for v in per_robot.values()), per_robot  # the near misses touched the cube
    assert out["grasp_edge_max_object_speed"] == max(per_robot.values()) <= HAND_SPEED, out
