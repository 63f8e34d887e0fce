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
import time

import numpy as np
import pytest

from tests.support import wait_until, xdotool
from tests.test_lerobot_plugin import BIN

pytestmark = pytest.mark.e2e
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


# -- lerobot-teleoperate: the page's gizmo drives an SO-101 follower -------------------------------------------------

FOLLOWER_ID = "follower_arm"


def expected_joint_change(move_m: np.ndarray) -> dict[str, float]:
    """Degrees each so101 joint turns (LeRobot's so101_follower units) when this tool's IK moves the hand `move_m`
    (world frame) from the home pose of the page's scene (lift, seed 0): the plugin's robot in ee_delta, in-process."""
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.robots import RobotConfig, make_robot_from_config

    ticks = 20
    config = RobotConfig.get_choice_class("mujoco_teleop")(robot="so101", scene="lift", seed=0, cameras="", action_space="ee_delta",
                                                           ee_step_m=float(np.linalg.norm(move_m)) / ticks)
    robot = make_robot_from_config(config)
    robot.connect()
    try:
        home = robot.get_observation()
        unit = move_m / np.linalg.norm(move_m)
        for _ in range(ticks):
            robot.send_action({"delta_x": unit[0], "delta_y": unit[1], "delta_z": unit[2], "gripper": 1.0})
        for _ in range(30):  # the arm settles on the target
            robot.send_action({"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0})
        moved = robot.get_observation()
        return {k: moved[k] - home[k] for k in home if k != "gripper.pos"}
    finally:
        robot.disconnect()


def test_lerobot_teleoperate_moves_an_so101_follower_with_the_pages_gizmo(tmp_path, browser):
    """`lerobot-teleoperate --robot.type=so101_follower --teleop.type=mujoco_teleop_web` against the Feetech emulator:
    a gizmo drag in headless Chromium moves the page's simulated so101, and the follower's Goal_Position packets turn
    each joint the way this tool's IK turns it for that move (signs; LeRobot's degrees through the calibration)."""
    import json
    import signal

    from tests import browser as headless
    from tests.servo_emulator import FeetechEmulator

    status_file, port = tmp_path / "status.json", headless.free_port()

    def status() -> dict:
        try:
            return json.loads(status_file.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            return {}

    with FeetechEmulator.start(tmp_path, role="follower", rate=3000) as arm:
        arm.write_calibration_file(tmp_path / "cal", FOLLOWER_ID)

        def goals() -> list[dict[str, float]]:
            rows: dict[float, dict[int, int]] = {}
            for w in arm.goal_log():
                rows.setdefault(w["t"], {})[w["id"]] = w["raw"]
            return [arm.action_of(raw) for _, raw in sorted(rows.items())]

        env = {**os.environ, "HF_HUB_OFFLINE": "1", "CUDA_VISIBLE_DEVICES": ""}
        argv = [str(BIN / "lerobot-teleoperate"), "--robot.type=so101_follower", f"--robot.port={arm.port}", f"--robot.id={FOLLOWER_ID}",
                f"--robot.calibration_dir={tmp_path / 'cal'}", "--teleop.type=mujoco_teleop_web", f"--teleop.port={port}",
                f"--teleop.status_file={status_file}", "--fps=30", "--display_data=false"]
        log = tmp_path / "stderr.txt"
        with log.open("w") as err:
            proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
            try:
                wait_until(lambda: (status().get("tick", 0) > 0 and len(goals()) > 5) or proc.poll() is not None, 600,
                           "the page's simulation and the follower's first goals")
                assert proc.poll() is None, log.read_text()[-4000:]
                assert f"127.0.0.1:{port}" in log.read_text()  # the page's URL on stderr, on loopback
                page = headless.open_page(browser, status()["url"])
                headless.dismiss_toasts(page)
                home_target, before = np.array(status()["target_pos"][0]), goals()[-1]
                # a loaded machine's software WebGL may draw the gizmo late: the drag is retried until it grabs it
                after = headless.drag_gizmo_until(page, status, lambda s: np.linalg.norm(np.array(s["target_pos"][0]) - home_target) > 0.03,
                                                  timeout_s=300)
                page.close()
                target = np.array(after["target_pos"][0])
                # the page's arm reaches the gizmo's target, then the follower's goals are that arm's joint targets
                wait_until(lambda: np.linalg.norm(np.array(status()["ee_pos"][0]) - target) < 0.01, 120, "the page's arm at the target")
                count = len(goals())
                wait_until(lambda: len(goals()) > count + 5, 120, "goals sent after the arm arrived")
                last = goals()[-1]
            finally:
                if proc.poll() is None:
                    proc.send_signal(signal.SIGINT)
                    try:
                        proc.wait(60)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                        proc.wait()
    want = expected_joint_change(target - home_target)
    turned = {k: last[k] - before[k] for k in want}
    big = [k for k in want if abs(want[k]) > 3.0]
    assert big, want  # the drag turned some joint by more than 3 degrees
    for k in big:
        assert np.sign(turned[k]) == np.sign(want[k]) and abs(turned[k]) > 0.3 * abs(want[k]), (k, turned, want)
