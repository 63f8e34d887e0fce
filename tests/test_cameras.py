"""Cameras framed on the task: the pixel figure on every task and robot, real exported pixels, `--camera`.

The figure (`object_px_at_96`, scenes.cameras.figure) is geometry: each task object's
bounding boxes projected through the compiled camera. It is checked here on every
built-in and library task with each robot the task lists (seed 0), against a hand
computation, and against the pixels of a real 96x96 export.
"""

from __future__ import annotations

import json
import math
import os
import shutil

import mujoco
import numpy as np
import pytest

from scenes.assembly.arena import room_camera
from scenes.assembly.build import build_scene
from scenes.cameras.figure import camera_figures, object_bodies
from scenes.cameras.view import CameraPose, fit_points, geom_corners, body_geoms, in_view, object_px, project
from scenes.cameras.extra import CameraSpecError, parse_camera
from scenes.assembly.framing import work_points
from scenes.tasks.registry import TASKS, find_task, library_tasks
from tests.support import PICK, ROOT, assert_one_line_error, record_script, run_cli, run_json

SCENES = [(name, robot) for name in [*TASKS, *library_tasks()] for robot in find_task(name).robots]
SIDE = "side=pos:0.47,-0.7,0.45;look_at:0.47,0,0.02;fovy:40"


# -- the geometry ---------------------------------------------------------------------------------------

def _box_scene(x: float = 0.0) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A 10 cm cube, top face 0.95 m below a camera looking straight down with a 90 degree fovy."""
    xml = f"""<mujoco><worldbody>
      <camera name="down" pos="0 0 1" xyaxes="1 0 0 0 1 0" fovy="90"/>
      <body name="cube" pos="{x} 0 0"><geom type="box" size=".05 .05 .05"/></body>
    </worldbody></mujoco>"""
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def test_object_px_is_the_projected_width_of_the_nearest_face():
    model, data = _box_scene()
    focal = 48 / math.tan(math.radians(45))  # px at 96x96
    assert object_px(model, data, "down", [model.body("cube").id]) == pytest.approx(focal * 0.1 / 0.95, abs=1e-9)
    assert object_px(model, data, "down", [model.body("cube").id], size=224) == pytest.approx(112 * 0.1 / 0.95, abs=1e-9)
    # At x = 0.95 the cube's faces start at u = 48 + 48 * 0.9 / 1.05 (the far face's edge) and run off the image at 96.
    half_out = _box_scene(x=0.95)
    assert object_px(*half_out, "down", [half_out[0].body("cube").id]) == pytest.approx(96 - 48 - 48 * 0.9 / 1.05, abs=1e-9)
    gone = _box_scene(x=3.0)
    assert object_px(*gone, "down", [gone[0].body("cube").id]) == 0.0


def test_a_fitted_camera_keeps_every_point_in_view_and_touches_the_margin():
    rng = np.random.default_rng(0)
    points = rng.uniform([0.2, -0.3, 0.0], [0.7, 0.2, 0.1], size=(40, 3))
    el = math.radians(50)
    forward = np.array([-math.cos(el), 0.0, -math.sin(el)])
    right = np.cross(forward, [0, 0, 1])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    pose = fit_points(points, right, up, fovy=30.0, margin=0.1)
    xml = (f'<mujoco><worldbody><camera name="c" pos="{" ".join(map(str, pose.pos))}" '
           f'xyaxes="{" ".join(map(str, pose.xyaxes))}" fovy="30"/></worldbody></mujoco>')
    model = mujoco.MjModel.from_xml_string(xml)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    uv, ahead = project(model, data, 0, points)
    assert ahead.all()
    assert (uv >= 0.1 * 48 - 1e-6).all() and (uv <= 96 - 0.1 * 48 + 1e-6).all()
    span = uv.max(axis=0) - uv.min(axis=0)
    assert max(span) == pytest.approx(0.9 * 96, abs=1e-6)  # as close as it can be: the tighter axis fills the image
    assert (uv.max(axis=0) + uv.min(axis=0)) / 2 == pytest.approx([48, 48], abs=1e-6)  # centred


@pytest.mark.parametrize("task_name, robot", SCENES, ids=[f"{t}-{r}" for t, r in SCENES])
def test_every_task_is_framed_for_every_robot(task_name, robot):
    """front >= 6 px and overhead >= 8 px for the smallest object at 96x96; every object and every goal
    region in view of both; the figure is far above the wide `room` view's."""
    scene = build_scene(task_name, robot, seed=0)
    figures = camera_figures(scene)
    assert figures["front"] >= 6.0, figures
    assert figures["overhead"] >= 8.0, figures
    assert figures["front"] > 1.5 * figures["room"], figures
    model, data = scene.model, scene.make_data()
    bodies = object_bodies(scene)
    assert len(bodies) == len(scene.task.objects)
    regions = [s for s in range(model.nsite) if model.site(s).name in scene.task.regions]
    corners = [geom_corners(model, data, body_geoms(model, b)) for b in bodies]
    for s in regions:  # a goal region's rectangle on the table
        half = model.site_size[s]
        corners.append(np.array([data.site_xpos[s] + [sx * half[0], sy * half[1], 0] for sx in (-1, 1) for sy in (-1, 1)]))
    area = work_points(scene.task, scene.layout, model)  # every start region, grown by its object, and goal region
    for camera in ("front", "overhead"):
        assert in_view(model, data, camera, area), f"{camera} cuts the work area"
        for c in corners:
            assert in_view(model, data, camera, c), f"{camera} cuts an object or region"


@pytest.mark.parametrize("task_name, robot", [("lift", "panda"), ("pick_place", "ur5e"), ("put_cube_in_drawer", "panda"),
                                              ("handover", "bimanual")])
def test_the_framing_is_the_same_for_every_seed(task_name, robot):
    """Cameras frame the task's regions, not one seed's placement: a dataset's episodes share one view."""
    a, b = build_scene(task_name, robot, seed=0), build_scene(task_name, robot, seed=5)
    for name in ("front", "overhead", "room"):
        assert np.allclose(a.model.camera(name).pos, b.model.camera(name).pos, atol=1e-6)
        assert np.allclose(a.model.camera(name).quat, b.model.camera(name).quat, atol=1e-6)


def test_room_is_the_earlier_front_view():
    """`room` keeps the wide view scenes had as `front` before the framing (robot and whole table)."""
    scene = build_scene("lift", "panda", seed=0)
    cx = scene.layout.center[0]
    dist = max(0.6, 2.2 * scene.layout.spread + 0.45)
    assert np.allclose(scene.model.camera("room").pos, [cx + 1.5 * dist, 0.6 * dist, 0.9 * dist], atol=1e-6)
    assert float(scene.model.cam_fovy[scene.model.camera("room").id]) == 50.0
    assert scene.cameras[:3] == ("front", "overhead", "room") and "wrist" in scene.cameras


def test_camera_specs_parse_or_say_what_is_wrong():
    cam = parse_camera("side=pos:1,0,1;look_at:0,0,0;fovy:40")
    assert cam.name == "side" and cam.pose.pos == (1.0, 0.0, 1.0) and cam.pose.fovy == 40.0
    assert parse_camera("top=pos:0.5,0,2;look_at:0.5,0,0").pose.fovy == 45.0  # straight down works too
    for bad, says in [("side", "expected NAME="), ("side=pos:1,0;look_at:0,0,0", "pos"), ("side=pos:1,0,1", "look_at missing"),
                      ("side=pos:1,0,1;look_at:1,0,1", "own position"), ("side=pos:1,0,1;look_at:0,0,0;fovy:0", "fovy"),
                      ("side=pos:1,0,1;look_at:0,0,0;zoom:2", "unknown part"), ("9x=pos:1,0,1;look_at:0,0,0", "NAME"),
                      ("side=pos:1,0,1;pos:1,0,1;look_at:0,0,0", "twice"), ("side=pos:a,b,c;look_at:0,0,0", "pos")]:
        with pytest.raises(CameraSpecError, match=says):
            parse_camera(bad)


def test_scenes_json_reports_each_cameras_figure():
    out = run_json("scenes", "--json", str(ROOT / "scenes" / "builtin_tasks" / "lift.toml"))
    row = out["scenes"][0]
    assert set(row["cameras"]) >= {"front", "overhead", "room"}
    front = row["cameras"]["front"]
    assert front["object_px_at_96"] == min(front["by_robot"].values()) >= 6
    assert set(front["by_robot"]) == set(row["robots"])
    assert front["by_robot"]["panda"] == camera_figures(build_scene("lift", "panda", 0))["front"]


# -- real pixels: an export at 96x96 ------------------------------------------------------------------

@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A scripted lift pick with the Panda, seed 0, as MCAP and HDF5."""
    rec = tmp_path_factory.mktemp("cameras") / "lift"
    record_script(rec, PICK, "--control-hz", "15", "--format", "both")
    return rec


def _frames(out, repo_id: str, key: str) -> np.ndarray:
    """Every frame of one camera as (T, H, W, 3) floats in 0..1."""
    os.environ["HF_HUB_OFFLINE"] = "1"
    from lerobot.datasets import LeRobotDataset

    ds = LeRobotDataset(repo_id, root=out)
    return np.stack([ds[i][key].numpy().transpose(1, 2, 0) for i in range(ds.num_frames)])


def test_export_front_at_96_shows_the_cube_6px_across_and_renders_an_added_camera(recorded, tmp_path):
    out = tmp_path / "ds"
    result = run_cli("export", str(recorded), "--out", str(out), "--repo-id", "t/cams", "--image-size", "96x96", "--no-video",
                     "--cameras", "front,side,room", "--camera", SIDE)
    assert result.returncode == 0, result.stderr[-3000:]
    front = _frames(out, "t/cams", "observation.images.front")
    side = _frames(out, "t/cams", "observation.images.side")
    room = _frames(out, "t/cams", "observation.images.room")
    assert front.shape[1:] == side.shape[1:] == (96, 96, 3)
    first = front[0]  # the start of seed 0: the cube where the seed put it, the arm at home
    r, g, b = first[..., 0], first[..., 1], first[..., 2]
    red = (r > 0.25) & (r > 2 * g) & (r > 2 * b)  # the cube is rgba (0.85, 0.2, 0.15): nothing else is that red
    cols = np.flatnonzero(red.any(axis=0))
    assert cols.size and cols[-1] - cols[0] + 1 >= 6, f"the cube spans {cols.size} columns in front"
    figure = camera_figures(build_scene("lift", "panda", seed=0))["front"]
    assert abs((cols[-1] - cols[0] + 1) - figure) <= 2.0  # the figure is the cube's projected width
    room_cols = np.flatnonzero(((room[0][..., 0] > 0.25) & (room[0][..., 0] > 2 * room[0][..., 1])).any(axis=0))
    assert room_cols.size < cols.size  # the wide view shows it smaller
    # The added camera renders the recorded states: a real picture that changes as the arm moves.
    assert side[0].std() > 0.03 and np.abs(side[-1] - side[0]).mean() > 0.002
    assert np.abs(side[0] - front[0]).mean() > 0.02


def test_bad_camera_flags_are_one_line_errors(recorded, tmp_path):
    for spec, says in [("side=pos:1,0;look_at:0,0,0", "pos"), ("side=pos:1,0,1;look_at:0,0,0;fovy:500", "fovy"),
                       ("front=pos:1,0,1;look_at:0,0,0", "'front'")]:
        result = run_cli("export", str(recorded), "--out", str(tmp_path / "x"), "--repo-id", "t/x", "--camera", spec)
        assert_one_line_error(result, says)
        assert not (tmp_path / "x").exists()


def _make_old(path) -> CameraPose:
    """Rewrite an HDF5 episode's embedded model as scenes were before the framing: `front` at today's
    `room` pose, no `room`, `overhead` straight down from 1.5 x the old distance. Returns that front pose."""
    import h5py

    scene = build_scene("lift", "panda", seed=0)
    old_front = room_camera(scene.layout)
    (cx, cy), dist = scene.layout.center, max(0.6, 2.2 * scene.layout.spread + 0.45)
    old_overhead = CameraPose(pos=(cx, cy, 1.5 * dist), xyaxes=(0, -1, 0, 1, 0, 0), fovy=45.0)
    with h5py.File(path, "r+") as f:
        demo = f["data/demo_0"]
        assets = {str(ds.attrs["name"]): ds[()].tobytes() for ds in demo["assets"].values()}
        spec = mujoco.MjSpec.from_string(str(demo.attrs["model_file"]), assets=assets)
        spec.delete(spec.camera("room"))
        for name, pose in (("front", old_front), ("overhead", old_overhead)):
            cam = spec.camera(name)
            cam.pos, cam.fovy = list(pose.pos), pose.fovy
            cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
            cam.alt.xyaxes = list(pose.xyaxes)
        spec.compile()
        demo.attrs["model_file"] = spec.to_xml()
        meta = json.loads(demo.attrs["teleop_meta"])
        meta["cameras"] = ["front", "overhead", "wrist"]
        demo.attrs["teleop_meta"] = json.dumps(meta)
    return old_front


def test_a_recording_made_before_exports_with_its_own_cameras(recorded, tmp_path):
    """An episode embeds its model: its cameras are the ones it was recorded with, whatever scenes frame now."""
    from replay import load_episode, replay_states
    from replay.render import FastRenderer

    old = tmp_path / "old"
    old.mkdir()
    path = old / "episode_000000.hdf5"
    shutil.copy(next(recorded.glob("*.hdf5")), path)
    front = _make_old(path)
    episode = load_episode(path)
    model = episode.build_model()
    assert [model.camera(i).name for i in range(model.ncam)] == ["front", "overhead", "wrist"]
    assert np.allclose(model.camera("front").pos, front.pos, atol=1e-5)
    missing = run_cli("export", str(old), "--out", str(tmp_path / "x"), "--repo-id", "t/x", "--cameras", "room")
    assert_one_line_error(missing, "'room'", "front, overhead, wrist")
    out = tmp_path / "ds"
    result = run_cli("export", str(old), "--out", str(out), "--repo-id", "t/old", "--image-size", "96x96", "--no-video",
                     "--cameras", "front")
    assert result.returncode == 0, result.stderr[-3000:]
    exported = _frames(out, "t/old", "observation.images.front")[0]
    with FastRenderer(model, 96, 96, ["front"]) as renderer:
        _, data = next(iter(replay_states(episode, model)))
        drawn = renderer.render(data, 0) / 255.0
    assert np.abs(exported - drawn).max() <= 1.5 / 255  # the old framing, pixel for pixel
