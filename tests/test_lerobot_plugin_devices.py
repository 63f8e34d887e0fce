"""LeRobot's own commands with devices on the simulation (issue 58): `lerobot-record` fed by LeRobot's `keyboard_ee`
teleoperator under Xvfb (keys sent by xdotool) in `ee_delta`; `lerobot-teleoperate` with this tool's page
(`mujoco_teleop_web`) driving an SO-101 follower on the Feetech emulator (its gizmo dragged in headless Chromium)
and driving the simulation.

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


# -- lerobot-teleoperate: the page's gizmo drives an SO-101 follower -------------------------------------------------

FOLLOWER_ID = "follower_arm"
# LeRobot's Feetech SDK gives a status packet ~34 ms. On the loaded 2-core machine a pseudo-terminal's bytes were
# measured arriving 50-515 ms late about once in 1,000-5,000 packets, whatever the two processes' priorities (the
# kernel moves pty bytes on a worker thread): LeRobot's default 2 retries of a sync read let such a stall end the
# whole command ("There is no status packet!"), the process gone while the page it served still shows in the browser.
# `num_read_retries` is LeRobot's own option for a bus that misses answers; its connect() writes are never retried,
# so a command that ends there on a missed answer is started again (tests/servo_emulator.py: connect_device).
READ_RETRIES = 10
BUS_LATE = ("There is no status packet", "Incorrect status packet", "Missing motor IDs")
DRAG_AXIS, DRAG_PIXELS = 1, 40.0  # the gizmo's y arrow (the target's frame: world -y), ~9 cm: well inside the so101's reach


def ik_joint_targets(target_pos=None, target_quat=None) -> dict[str, float]:
    """The so101's joint targets (LeRobot's so101_follower degrees) that this tool's IK gives for an EE target in
    the page's scene (lift, seed 0; None: the home target), once settled: the IK converges to the same joints
    whatever path the target took there (a drag's steps or one jump, measured equal to 0.001 deg)."""
    from devices.command import Command
    from teleop.learn.gym_env import TeleopEnv

    env = TeleopEnv("lift", "so101", control_hz=float(FPS), cameras=[], seed=0, object_state=False)
    try:
        session = env.session
        if target_pos is not None:
            session.step([Command(target_pos=np.asarray(target_pos, dtype=float), target_quat=np.asarray(target_quat, dtype=float),
                                  source="test")])
        for _ in range(100):
            session.step([])
        arm = env.arms[0]
        ctrl = np.asarray(session.controller.data.ctrl, dtype=float)[arm.ctrl_ids]
        return {f"{name}.pos": float(np.degrees(q)) for name, q in zip(env.features["observation.state"]["names"], ctrl)}
    finally:
        env.close()


def test_lerobot_teleoperate_moves_an_so101_follower_with_the_pages_gizmo(tmp_path, browser):
    """`lerobot-teleoperate --robot.type=so101_follower --teleop.type=mujoco_teleop_web` against the Feetech emulator:
    a gizmo drag in headless Chromium moves the page's simulated so101, and the follower's Goal_Position packets (read
    back through the calibration, LeRobot's degrees) are the joint targets this tool's IK gives for the dragged
    target, joint by joint, to one servo step; before the drag, those of the home pose."""
    import json
    import signal

    from tests import browser as headless
    from tests.servo_emulator import FeetechEmulator

    status_file, port = tmp_path / "status.json", headless.free_port()
    log = tmp_path / "stderr.txt"

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
            return [arm.action_of(raw) for _, raw in sorted(rows.items()) if len(raw) == len(arm.ids)]

        def near(action: dict[str, float], want: dict[str, float]) -> bool:
            return all(abs(action[k] - want[k]) <= arm.tolerance(k.removesuffix(".pos")) + 0.05 for k in want)

        env = {**os.environ, "HF_HUB_OFFLINE": "1", "CUDA_VISIBLE_DEVICES": ""}
        argv = [str(BIN / "lerobot-teleoperate"), "--robot.type=so101_follower", f"--robot.port={arm.port}", f"--robot.id={FOLLOWER_ID}",
                f"--robot.calibration_dir={tmp_path / 'cal'}", f"--robot.num_read_retries={READ_RETRIES}",
                "--teleop.type=mujoco_teleop_web", f"--teleop.port={port}", f"--teleop.status_file={status_file}",
                f"--fps={FPS}", "--display_data=false"]
        proc = None

        def alive() -> bool:
            assert proc.poll() is None, f"lerobot-teleoperate ended ({proc.returncode}):\n{log.read_text()[-4000:]}"
            return True

        try:
            for attempt in range(3):
                status_file.unlink(missing_ok=True)
                with log.open("w") as err:
                    proc = subprocess.Popen(argv, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=err)
                started = len(goals())
                if attempt == 0:  # while the command imports LeRobot and torch
                    home_want = ik_joint_targets()
                wait_until(lambda: proc.poll() is not None or ("lerobot_action" in status() and len(goals()) > started + 5), 600,
                           "the page's simulation and the follower's first goals")
                if proc.poll() is None:
                    break
                if attempt == 2 or not any(sign in log.read_text() for sign in BUS_LATE):
                    alive()  # fails with the log
            assert f"127.0.0.1:{port}" in log.read_text()  # the page's URL on stderr, on loopback
            # before the drag the follower holds the page's home pose: the IK's joints, the gripper open
            assert near(goals()[-1], home_want) and goals()[-1]["gripper.pos"] > 99.0, (goals()[-1], home_want)
            page = headless.open_page(browser, status()["url"])
            headless.dismiss_toasts(page)
            home_target = np.array(status()["target_pos"][0])
            # a loaded machine's software WebGL may draw the gizmo late: the drag is retried until it grabs it
            headless.drag_gizmo_until(page, lambda: alive() and status(),
                                      lambda s: np.linalg.norm(np.array(s["target_pos"][0]) - home_target) > 0.03,
                                      axis=DRAG_AXIS, pixels=DRAG_PIXELS, timeout_s=300)
            page.close()  # the drag is over: the target stays where it was let go
            after = status()
            target, quat = np.array(after["target_pos"][0]), np.array(after["target_quat"][0])
            want = ik_joint_targets(target, quat)
            turned = [k for k in want if abs(want[k] - home_want[k]) > 3.0]
            assert len(turned) >= 3, (want, home_want)  # the drag turns several joints by more than 3 degrees
            # the page's arm settles on the IK's joints, and the follower is sent exactly those
            wait_until(lambda: alive() and near(status()["lerobot_action"]["values"], want), 120, "the page's arm at the dragged target")
            wait_until(lambda: alive() and near(goals()[-1], want), 60, "the follower's goals at the dragged target's joints")
            assert status()["target_pos"][0] == after["target_pos"][0]  # nothing moved the target after the drag
        finally:
            if proc is not None and proc.poll() is None:
                proc.send_signal(signal.SIGINT)
                try:
                    proc.wait(60)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()


def test_lerobot_teleoperate_drives_the_simulation_with_the_pages_joint_targets(tmp_path):
    """`lerobot-teleoperate --robot.type=mujoco_teleop --teleop.type=mujoco_teleop_web` (the page's simulation and the
    driven one in one process, no browser): it runs for --teleop_time_s and ends cleanly, the page's simulation ticks,
    and the driven so101's recorded joint targets are the page's action (LeRobot's degrees back to radians): at rest,
    the home pose's IK joints."""
    import json

    from replay import load_episode
    from tests.browser import free_port

    status_file = tmp_path / "status.json"
    argv = [str(BIN / "lerobot-teleoperate"), "--robot.type=mujoco_teleop", "--robot.robot=so101", "--robot.scene=lift",
            "--robot.cameras=", f"--robot.record_dir={tmp_path / 'eps'}", "--teleop.type=mujoco_teleop_web",
            f"--teleop.port={free_port()}", f"--teleop.status_file={status_file}", "--teleop_time_s=3", f"--fps={FPS}",
            "--display_data=false"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "CUDA_VISIBLE_DEVICES": ""}
    done = subprocess.run(argv, cwd=tmp_path, env=env, stdin=subprocess.DEVNULL, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-4000:]
    status = json.loads(status_file.read_text())
    action = status["lerobot_action"]
    assert status["error"] is None and status["tick"] > 0 and action["tick"] > 0
    (path,) = sorted((tmp_path / "eps").glob("episode_*.mcap"))
    episode = load_episode(path)
    assert episode.steps >= 5 and episode.meta.devices == ("lerobot",)
    model = episode.build_model()
    joints = episode.meta.arms[0].joints
    acts = [next(a for a in range(model.nu) if model.actuator_trnid[a, 0] == model.joint(j).id) for j in joints]
    want = np.radians([action["values"][f"{j}.pos"] for j in joints])
    assert np.allclose(episode.ctrl[-1, acts], want, atol=1e-9)  # the last tick was driven by the page's newest action
    assert np.allclose(np.degrees(want), [ik_joint_targets()[f"{j}.pos"] for j in joints], atol=0.05)  # the home pose's IK


def test_the_pages_action_is_published_per_tick_and_a_stopped_simulation_ends_get_action(tmp_path):
    """In-process: `get_action` is the newest tick's published targets, the status file's `lerobot_action` the same;
    once the page's simulation stops on an error (a step that raises, injected), `get_action` raises it instead of
    returning a frozen target forever."""
    import json

    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.teleoperators import TeleoperatorConfig, make_teleoperator_from_config

    status_file = tmp_path / "status.json"
    teleoperator = make_teleoperator_from_config(TeleoperatorConfig.get_choice_class("mujoco_teleop_web")(status_file=status_file))
    teleoperator.connect()
    try:
        sim = teleoperator.app.sim
        wait_until(lambda: sim.snapshot.tick > 3, 120, "the page's simulation ticking")
        action = teleoperator.get_action()
        assert all(abs(action[k] - v) < 0.05 for k, v in ik_joint_targets().items()), action  # the home pose's IK joints
        wait_until(lambda: status_file.exists() and "lerobot_action" in status_file.read_text(), 60, "the status file")
        published = json.loads(status_file.read_text())["lerobot_action"]
        assert published["tick"] > 0 and published["values"] == pytest.approx(teleoperator.get_action())

        def broken(*args, **kwargs):
            raise FloatingPointError("injected")

        teleoperator.env.session.step = broken
        wait_until(lambda: sim.error is not None, 60, "the page's simulation to stop")
        with pytest.raises(RuntimeError, match="injected"):
            teleoperator.get_action()
    finally:
        teleoperator.disconnect()
