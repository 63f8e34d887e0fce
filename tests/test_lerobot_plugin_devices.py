"""LeRobot's own commands with devices on the simulation (issue 58): `lerobot-record` fed by LeRobot's `keyboard_ee`
teleoperator under Xvfb (keys sent by xdotool) in `ee_delta`.

LeRobot's keyboard teleoperators listen through pynput, which needs an X11 DISPLAY: a private Xvfb
(conftest.py's `xvfb`). lerobot-record's own listener reads the same keys: Right / Left arrows (and n, r, q) end
or re-record its episode, so only keyboard_ee's Up / Down (delta_y -1 / +1) and Shift_L / Shift_R (delta_z -1 / +1)
are sent here. Units: metres (EE positions in the world frame), ee_step_m metres per delta unit.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.support import wait_until, xdotool

pytestmark = pytest.mark.e2e
BIN = Path(sys.executable).parent  # the venv's LeRobot commands
FPS = 30
STEP_M = 0.002  # metres per delta unit a tick: 1.5 s of a held key at 30 fps is 9 cm of target


def ee_positions(robot_name: str, names: list[str], states: np.ndarray) -> np.ndarray:
    """The EE site's world position (m) of each dataset state row (forward kinematics of the plugin's own model)."""
    import mujoco

    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.robots import RobotConfig, make_robot_from_config

    robot = make_robot_from_config(RobotConfig.get_choice_class("mujoco_teleop")(robot=robot_name, cameras=""))
    model, arm = robot.env.model, robot.env.arms[0]
    data = mujoco.MjData(model)
    out = []
    for row in states:
        values = robot.units.from_lerobot(dict(zip(names, row.tolist())))
        for joint, q in zip(arm.joints, values):
            data.qpos[model.joint(joint).qposadr[0]] = q
        mujoco.mj_kinematics(model, data)
        out.append(data.site_xpos[arm.site_id].copy())
    robot.env.close()
    return np.array(out)


@pytest.fixture(scope="module")
def keyboard_recorded(tmp_path_factory, xvfb):
    """`lerobot-record --teleop.type=keyboard_ee` on the simulated panda in ee_delta, one 5 s episode, with the
    watch-only page (`--robot.view=true`): once recording starts, Shift_R is held 1.5 s (up), then Up 1.5 s (delta_y
    -1: towards -y); between the two the page is fetched (one LeRobot command for both: each costs torch's import)."""
    import urllib.request

    from tests.browser import free_port

    tmp = tmp_path_factory.mktemp("lerobot_keyboard")
    env = {k: v for k, v in os.environ.items() if k not in ("WAYLAND_DISPLAY", "XDG_SESSION_TYPE")}
    env.update(DISPLAY=xvfb, HF_HUB_OFFLINE="1", WANDB_MODE="disabled", CUDA_VISIBLE_DEVICES="")
    log, view_port, page = tmp / "stderr.txt", free_port(), {}
    argv = [str(BIN / "lerobot-record"), "--robot.type=mujoco_teleop", "--robot.robot=panda", "--robot.scene=lift", "--robot.seed=0",
            f"--robot.fps={FPS}", "--robot.cameras=", "--robot.action_space=ee_delta", f"--robot.ee_step_m={STEP_M}",
            "--robot.view=true", f"--robot.view_port={view_port}",
            "--teleop.type=keyboard_ee", "--dataset.repo_id=local/kb", f"--dataset.root={tmp / 'ds'}", "--dataset.num_episodes=1",
            "--dataset.episode_time_s=5", "--dataset.reset_time_s=0", f"--dataset.fps={FPS}", "--dataset.push_to_hub=false",
            "--dataset.single_task=Lift the hand, then move it along -y.", "--dataset.video=false", "--display_data=false",
            "--play_sounds=false"]
    with log.open("w") as err:
        proc = subprocess.Popen(argv, cwd=tmp, env=env, stdin=subprocess.DEVNULL, stdout=err, stderr=subprocess.STDOUT)
        try:
            wait_until(lambda: "Recording episode 0" in log.read_text() or proc.poll() is not None, 600, "lerobot-record's first episode")
            assert proc.poll() is None, log.read_text()[-4000:]
            for key in ("Shift_R", "Up"):
                xdotool(xvfb, "keydown", key)
                time.sleep(1.5)
                xdotool(xvfb, "keyup", key)
                if not page:
                    with urllib.request.urlopen(f"http://127.0.0.1:{view_port}/", timeout=60) as answer:
                        page.update(status=answer.status, body=answer.read(), recording=proc.poll() is None)
            assert proc.wait(600) == 0, log.read_text()[-4000:]
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    from lerobot.datasets import LeRobotDataset

    dataset = LeRobotDataset("local/kb", root=tmp / "ds")
    frames = dataset.hf_dataset.with_format("numpy")
    return {"dataset": dataset, "action": np.stack(frames["action"]), "state": np.stack(frames["observation.state"]),
            "page": page, "stderr": log.read_text(), "view_port": view_port}


def test_lerobot_record_with_keyboard_ee_moves_the_hand_the_way_the_keys_said(keyboard_recorded):
    dataset, action, state = keyboard_recorded["dataset"], keyboard_recorded["action"], keyboard_recorded["state"]
    features = dataset.meta.features
    assert features["action"]["names"] == ["delta_x", "delta_y", "delta_z", "gripper"] and dataset.num_episodes == 1
    dx, dy, dz = action[:, 0], action[:, 1], action[:, 2]
    up, side = np.flatnonzero(dz == 1.0), np.flatnonzero(dy == -1.0)
    assert len(up) >= 5 and len(side) >= 5, (dy.tolist(), dz.tolist())  # both keys were read (fewer frames on a slow loop)
    assert np.all(dx == 0.0) and np.all(np.isin(dz, (0.0, 1.0))) and np.all(np.isin(dy, (0.0, -1.0)))
    assert up[-1] < side[0]  # in the order they were pressed: Shift_R, then Up
    assert np.all(action[:, 3] == 1.0)  # no gripper key: keep
    ee = ee_positions("panda", list(features["observation.state"]["names"]), state)
    # while Shift_R was held and just after (the arm follows its target a few ticks behind) the hand rose; then
    # while Up was held it went towards -y; each by at least half of what the keys commanded
    rise = ee[side[0], 2] - ee[up[0], 2]
    assert rise > 0.5 * len(up) * STEP_M, (rise, len(up))
    shift = ee[-1, 1] - ee[side[0], 1]
    assert shift < -0.5 * len(side) * STEP_M, (shift, len(side))
    assert abs(ee[-1, 0] - ee[0, 0]) < 0.02  # no x key: x stayed (IK settling only)
    assert abs(ee[-1, 2] - ee[side[0], 2]) < 0.02  # and the height held while it moved sideways


def test_the_watch_only_page_answers_while_lerobot_record_runs(keyboard_recorded):
    """`--robot.view=true`: the session page was served (200, viser's page) while the episode was being recorded,
    on loopback, its URL on stderr; and the ticks that LeRobot drove through it are the ones recorded (the EE test)."""
    page = keyboard_recorded["page"]
    assert page["status"] == 200 and page["recording"] and b"<html" in page["body"].lower()
    assert f"watch the simulation at http://127.0.0.1:{keyboard_recorded['view_port']}" in keyboard_recorded["stderr"]
    assert "drawing failed" not in keyboard_recorded["stderr"] and "panel refresh failed" not in keyboard_recorded["stderr"]


def test_the_watch_only_page_shows_the_robots_ticks_and_drives_nothing():
    """In-process: with view=true each send_action is one tick of the page's session (its snapshot and status follow
    the robot's simulation), the page's own loop never runs, and its controls are disabled."""
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.robots import RobotConfig, make_robot_from_config

    robot = make_robot_from_config(RobotConfig.get_choice_class("mujoco_teleop")(robot="so101", cameras="", action_space="ee_delta",
                                                                                view=True))
    robot.connect()
    try:
        app = robot.view.app
        assert app.host == "127.0.0.1" and app.gizmo is None and app.sim.devices == [robot.view.feed]
        for _ in range(10):
            robot.send_action({"delta_x": 0.0, "delta_y": 0.0, "delta_z": 1.0, "gripper": 1.0})
        controller = robot.env.session.controller
        status = app.status()
        assert status["tick"] == 10 and not app.sim.alive
        assert np.allclose(status["target_pos"][0], controller.target_pose(0)[0], atol=1e-5)
        assert np.allclose(status["ee_pos"][0], controller.ee_pose(0)[0], atol=1e-5)
        panel = app.panel
        assert all(c.disabled for c in (panel.record_btn, panel.save_btn, panel.discard_btn, panel.reset_btn, panel.pos_slider))
    finally:
        robot.disconnect()
    assert robot.view is None
