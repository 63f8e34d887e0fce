"""LeRobot's own commands on the simulation (issue 58): the plugin's robot, env and import, run as a user runs them.

`lerobot-record --robot.type=mujoco_teleop --teleop.type=so101_leader` reads LeRobot's real SOLeader over a
Feetech emulator on a pseudo-terminal (tests/servo_emulator.py); `lerobot-train` and `lerobot-eval` run with
`--env.type=mujoco_teleop` on a small ACT checkpoint trained on a `teleop export`, and `teleop eval` runs the same
checkpoint on the same seeds. Each LeRobot command imports torch (slow on 2 cores): one run of each, shared by
module-scoped fixtures. Units: LeRobot's so101 degrees and gripper 0..100 where it says so.
"""

from __future__ import annotations

import functools
import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.servo_emulator import FeetechEmulator
from tests.support import PICK, ROOT, run_cli, run_json, run_script
from tests.test_leader_device import so_motion

os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever

BIN = Path(sys.executable).parent
TASK = "Pick up the red cube and lift it."
FPS = 30
CAMERAS = ("front", "wrist")
SO101_KEYS = ["shoulder_pan.pos", "shoulder_lift.pos", "elbow_flex.pos", "wrist_flex.pos", "wrist_roll.pos", "gripper.pos"]
pytestmark = pytest.mark.e2e


def lerobot(command: str, *flags: str, cwd: Path, timeout: float = 900) -> subprocess.CompletedProcess:
    """A LeRobot console script, as a user runs it (its own process; the plugin found by its distribution name)."""
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "CUDA_VISIBLE_DEVICES": ""}
    result = run_script([str(BIN / command), *flags], env, cwd, timeout, ignore=("WANDB_MODE", "CUDA_VISIBLE_DEVICES"))
    assert result.returncode == 0, f"{command} exited {result.returncode}: {result.stderr[-4000:]}"
    return result


# -- the plugin's import --------------------------------------------------------------------------------------------


def test_the_plugin_imports_light_and_registers_all_three_types_when_lerobot_loads():
    """A fresh interpreter: the plugin package loads no MuJoCo, torch or viser; once LeRobot's registries load (as
    every LeRobot command loads them), the robot, teleoperator and env types are there."""
    code = (
        "import sys, json, importlib.metadata as m\n"
        "import lerobot_robot_mujoco_teleop\n"
        "heavy = sorted(n for n in ('mujoco', 'torch', 'viser', 'lerobot.robots') if n in sys.modules)\n"
        "from lerobot.robots.config import RobotConfig\n"
        "from lerobot.teleoperators.config import TeleoperatorConfig\n"
        "from lerobot.envs.configs import EnvConfig\n"
        "print(json.dumps({'heavy': heavy, 'dist': m.version('lerobot_robot_mujoco_teleop'),\n"
        "    'robot': RobotConfig.get_choice_class('mujoco_teleop').__name__,\n"
        "    'teleop': TeleoperatorConfig.get_choice_class('mujoco_teleop_web').__name__,\n"
        "    'env': EnvConfig.get_choice_class('mujoco_teleop').__name__}))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, cwd=ROOT.parent)
    assert out.returncode == 0, out.stderr[-3000:]
    report = json.loads(out.stdout.strip().splitlines()[-1])
    assert report["heavy"] == []
    assert report["dist"]  # installed as its own distribution (./run.sh test installs it): LeRobot finds it by name
    assert (report["robot"], report["teleop"], report["env"]) == ("MujocoTeleopConfig", "MujocoTeleopWebConfig", "MujocoTeleopEnvConfig")


# -- lerobot-record with a leader arm ---------------------------------------------------------------------------------


def leader_motion(t: float) -> dict[str, float]:
    """The leader's motion (radians): a 0.5 Hz sine on shoulder_pan and elbow_flex; the other joints at 0."""
    return {"shoulder_pan": 0.4 * math.sin(math.pi * t), "elbow_flex": 0.3 * math.sin(math.pi * t)}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """`lerobot-record` of 2 two-second episodes on the simulated so101 driven by an emulated SO-101 leader, two 96x96
    cameras, images (not video: lossless, compared exactly), and this tool's own episodes alongside."""
    tmp = tmp_path_factory.mktemp("lerobot_record")
    with FeetechEmulator.start(tmp, role="leader") as leader:
        leader.write_calibration_file(tmp / "cal", "arm")
        leader.play(so_motion(leader, leader_motion, 2.0, gripper=lambda t: 50 + 30 * math.sin(math.pi * t)))
        result = lerobot(
            "lerobot-record", "--robot.type=mujoco_teleop", "--robot.robot=so101", "--robot.scene=lift", "--robot.seed=0",
            f"--robot.fps={FPS}", f"--robot.cameras={','.join(CAMERAS)}", f"--robot.record_dir={tmp / 'eps'}",
            "--teleop.type=so101_leader", f"--teleop.port={leader.port}", "--teleop.id=arm", f"--teleop.calibration_dir={tmp / 'cal'}",
            # LeRobot's default 2 retries of a read: on a loaded machine the emulator's process can miss all three
            # ("There is no status packet!"), and lerobot-record ends
            "--teleop.num_read_retries=10",
            "--dataset.repo_id=local/sim", f"--dataset.root={tmp / 'ds'}", "--dataset.num_episodes=2", "--dataset.episode_time_s=2",
            "--dataset.reset_time_s=0.5", f"--dataset.fps={FPS}", "--dataset.push_to_hub=false", f"--dataset.single_task={TASK}",
            "--dataset.video=false", "--display_data=false", "--play_sounds=false", cwd=tmp)
    from lerobot.datasets import LeRobotDataset

    dataset = LeRobotDataset("local/sim", root=tmp / "ds")
    frames = dataset.hf_dataset.with_format("numpy")
    episode = np.asarray(frames["episode_index"])
    return {"tmp": tmp, "dataset": dataset, "episode": episode, "action": np.stack(frames["action"]),
            "state": np.stack(frames["observation.state"]), "stderr": result.stderr}


@functools.cache
def initial_observation(seed: int) -> dict:
    """What the plugin's robot observes at `seed`'s initial state (made here, in this process; once a seed: a robot
    with two cameras to build and render)."""
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.robots import RobotConfig, make_robot_from_config

    robot = make_robot_from_config(RobotConfig.get_choice_class("mujoco_teleop")(robot="so101", scene="lift", seed=seed,
                                                                                cameras=",".join(CAMERAS)))
    robot.connect()
    try:
        return robot.get_observation()
    finally:
        robot.disconnect()


def test_the_dataset_has_the_real_so101_followers_features(recorded):
    """Names, units and shapes of LeRobot's so101_follower with two 96x96 cameras: sim and real data train one policy."""
    from lerobot.cameras.opencv import OpenCVCameraConfig
    from lerobot.robots.so_follower import SOFollower, SOFollowerRobotConfig
    from lerobot.utils.feature_utils import hw_to_dataset_features

    cameras = {c: OpenCVCameraConfig(index_or_path=0, width=96, height=96, fps=FPS) for c in CAMERAS}
    real = SOFollower(SOFollowerRobotConfig(port="/dev/null", id="sim", calibration_dir=recorded["tmp"] / "real_cal", cameras=cameras))
    want = {**hw_to_dataset_features(real.observation_features, "observation", use_video=False),
            **hw_to_dataset_features(real.action_features, "action", use_video=False)}
    got = recorded["dataset"].meta.features
    for key, feature in want.items():
        assert got[key]["dtype"] == feature["dtype"] and tuple(got[key]["shape"]) == tuple(feature["shape"]), key
        assert list(got[key]["names"]) == list(feature["names"]), key
    assert got["observation.state"]["names"] == SO101_KEYS and recorded["dataset"].meta.robot_type == "mujoco_teleop"


def test_two_episodes_follow_the_leader_and_each_starts_at_its_seeds_initial_state(recorded):
    dataset, episode, action, state = recorded["dataset"], recorded["episode"], recorded["action"], recorded["state"]
    assert dataset.num_episodes == 2 and sorted(set(episode.tolist())) == [0, 1]
    for e in (0, 1):
        a, s = action[episode == e], state[episode == e]
        assert len(a) >= 5  # ~30 frames a second; a loaded machine runs slower
        # the action is the leader's reading in degrees (the sine's 0.4 rad = 22.9 deg, 0.3 rad = 17.2 deg)
        assert np.all(np.abs(a[:, 0]) <= 23.5) and np.all(np.abs(a[:, 2]) <= 18.0) and np.all(np.abs(a[:, [1, 3, 4]]) < 1.0)
        assert np.ptp(a[:, 0]) > 8.0  # it moved
        # the simulated joints follow, a few ticks behind (position servos; ticks are simulated time, so on a slow loop
        # the leader moves further between them: the shape is compared, not the distance)
        lag = 3
        assert np.corrcoef(s[lag:, 0], a[:-lag, 0])[0, 1] > 0.8 and np.corrcoef(s[lag:, 2], a[:-lag, 2])[0, 1] > 0.8
        assert np.ptp(s[:, 0]) > 0.5 * np.ptp(a[:, 0])
    # the first frame of each episode is its seed's initial state (seed 0, then 1), images included, exactly
    first = [int(np.flatnonzero(episode == e)[0]) for e in (0, 1)]
    for e, seed in ((0, 0), (1, 1)):
        want = initial_observation(seed)
        frame = dataset[first[e]]
        assert np.allclose(state[first[e]], [want[k] for k in SO101_KEYS], atol=1e-4)
        for cam in CAMERAS:
            image = (frame[f"observation.images.{cam}"].numpy() * 255).round().astype(np.uint8).transpose(1, 2, 0)
            assert image.shape == (96, 96, 3) and np.array_equal(image, want[cam]), (e, cam)
    assert not np.array_equal(initial_observation(0)["front"], initial_observation(1)["front"])  # two scenes (the cube moved)
    # never where the last one ended: episode 1 starts back at the initial pose, not at episode 0's last
    assert np.max(np.abs(state[first[1]] - state[first[1] - 1])) > 1.0


def test_this_tools_own_episodes_were_recorded_alongside_and_replay_bit_exact(recorded):
    from replay import load_episode, resimulate

    files = sorted((recorded["tmp"] / "eps").glob("episode_*.mcap"))
    assert len(files) == 2
    for seed, path in enumerate(files):
        episode = load_episode(path)
        assert episode.meta.seed == seed and episode.meta.devices == ("lerobot",) and episode.meta.source == "human"
        assert episode.steps >= int(np.sum(recorded["episode"] == seed))  # the dataset's frames, then the reset period's
        assert resimulate(episode).bit_exact
        # each tick's joint targets are the dataset's action at that frame (LeRobot's degrees -> radians), exactly
        model = episode.build_model()
        joints = episode.meta.arms[0].joints
        acts = [next(a for a in range(model.nu) if model.actuator_trnid[a, 0] == model.joint(j).id) for j in joints]
        action = recorded["action"][recorded["episode"] == seed]
        assert np.allclose(episode.ctrl[:len(action), acts], np.radians(action[:, :len(joints)].astype(np.float64)), atol=1e-6)


def test_lerobot_replay_on_the_episodes_seed_reproduces_it(recorded):
    """`lerobot-replay` of episode 1 with `--robot.seed=1` (its seed) replays it: this tool's record of the replay
    follows the recorded episode's joints (the dataset keeps the actions as float32: within a hair, not bit for bit)."""
    from replay import load_episode

    tmp = recorded["tmp"]
    lerobot("lerobot-replay", "--robot.type=mujoco_teleop", "--robot.robot=so101", "--robot.scene=lift", "--robot.seed=1",
            f"--robot.fps={FPS}", "--robot.cameras=", f"--robot.record_dir={tmp / 'replayed'}", "--dataset.repo_id=local/sim",
            f"--dataset.root={tmp / 'ds'}", "--dataset.episode=1", f"--dataset.fps={FPS}", "--play_sounds=false", cwd=tmp)
    (path,) = sorted((tmp / "replayed").glob("episode_*.mcap"))
    replayed, original = load_episode(path), load_episode(sorted((tmp / "eps").glob("episode_*.mcap"))[1])
    frames = int(np.sum(recorded["episode"] == 1))
    assert replayed.meta.seed == original.meta.seed == 1 and replayed.steps == frames
    assert np.array_equal(replayed.qpos[0], original.qpos[0])  # the seed's initial state
    assert np.max(np.abs(replayed.qpos[:frames] - original.qpos[:frames])) < 1e-3  # rad (or m)


# -- lerobot-train with evaluation in the simulation, then lerobot-eval against teleop eval ----------------------------

EVAL_HZ = 15  # the recorded picks' rate, so the export's fps and the env's
EVAL_SEEDS = (1000, 1001, 1002)
EVAL_STEPS = 15  # one simulated second


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """2 scripted picks -> a state-only export (joints, objects, EE pose) -> `lerobot-train` ACT, 2 steps, evaluated once
    in the simulation during training (`--env.type=mujoco_teleop --env_eval_freq=2`)."""
    root = tmp_path_factory.mktemp("lerobot_train")
    run_json("run", "--device", f"script:{PICK}", "--record", str(root / "eps"), "--control-hz", str(EVAL_HZ),
             "--episodes", "2", "--json")
    result = run_cli("export", str(root / "eps"), "--out", str(root / "ds"), "--repo-id", "test/lift", "--cameras", "none")
    assert result.returncode == 0, result.stderr[-3000:]
    train = lerobot(
        "lerobot-train", "--dataset.repo_id=test/lift", f"--dataset.root={root / 'ds'}", "--policy.type=act",
        "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.pretrained_backbone_weights=null", "--steps=2",
        "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={root / 'out'}",
        "--env.type=mujoco_teleop", "--env.task=lift", "--env.robot=panda", f"--env.fps={EVAL_HZ}", "--env.episode_length=6",
        "--env_eval_freq=2", "--eval.n_episodes=1", "--eval.batch_size=1", "--save_freq=2", cwd=root)
    model = root / "out" / "checkpoints" / "last" / "pretrained_model"
    assert (model / "config.json").is_file()
    return {"root": root, "model": model, "train_log": train.stdout + train.stderr}


def test_lerobot_train_evaluates_in_the_simulation(trained):
    """The evaluation ran in the env: its video of the simulation exists, rendered (rgb_array) at the front camera."""
    log = trained["train_log"]
    assert "'task_group': 'mujoco_teleop'" in log and "pc_success" in log, log[-3000:]
    named = re.findall(r"'video_paths': \['([^']+\.mp4)'", log)
    videos = [p if p.is_absolute() else trained["root"] / p for p in map(Path, named)]
    assert videos and videos[0].is_file() and videos[0].stat().st_size > 1000, (named, log[-3000:])
    import av

    with av.open(str(videos[0])) as video:
        frames = [f.to_ndarray(format="rgb24") for f in video.decode(video=0)]
    assert len(frames) >= 6 and frames[0].shape[2] == 3 and frames[0].std() > 5  # a rendered scene, not a blank frame


def test_lerobot_eval_and_teleop_eval_give_the_same_successes_on_the_same_seeds(trained):
    root, model = trained["root"], trained["model"]
    lerobot("lerobot-eval", f"--policy.path={model}", "--policy.device=cpu", "--env.type=mujoco_teleop", "--env.task=lift",
            "--env.robot=panda", f"--env.fps={EVAL_HZ}", f"--env.episode_length={EVAL_STEPS}", f"--eval.n_episodes={len(EVAL_SEEDS)}",
            "--eval.batch_size=1", f"--seed={EVAL_SEEDS[0]}", f"--output_dir={root / 'lerobot_eval'}", cwd=root)
    info = json.loads((root / "lerobot_eval" / "eval_info.json").read_text())
    (task,) = info["per_task"]
    assert task["task_group"] == "mujoco_teleop"
    lerobot_successes = [bool(s) for s in task["metrics"]["successes"]]  # one rollout a seed, in seed order (batch size 1)
    ours = run_json("eval", "--policy", str(model), "--scene", "lift", "--robot", "panda", "--episodes", str(len(EVAL_SEEDS)),
                    "--seed", str(EVAL_SEEDS[0]), "--max-seconds", str(EVAL_STEPS / EVAL_HZ), "--json", timeout=900)
    assert [e["seed"] for e in ours["per_episode"]] == list(EVAL_SEEDS) and ours["control_hz"] == EVAL_HZ
    assert all(e["steps"] <= EVAL_STEPS for e in ours["per_episode"])
    assert lerobot_successes == [e["success"] for e in ours["per_episode"]]
    assert info["overall"]["n_episodes"] == len(EVAL_SEEDS)


def test_the_env_gives_lerobot_its_keys_and_the_exports_features(trained):
    """In-process: the config's features are the export's (shapes of the dataset the checkpoint was trained on), and
    LeRobot's own preprocess_observation turns the env's observation into exactly the policy's input keys."""
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.envs.configs import EnvConfig
    from lerobot.envs.utils import env_to_policy_features, preprocess_observation

    cfg = EnvConfig.get_choice_class("mujoco_teleop")(task="lift", robot="panda", fps=EVAL_HZ, episode_length=4)
    exported = json.loads((trained["root"] / "ds" / "meta" / "info.json").read_text())["features"]
    policy = env_to_policy_features(cfg)
    for key, feature in policy.items():
        assert tuple(feature.shape) == tuple(exported[key]["shape"]), key
    vec = cfg.create_envs(n_envs=1)["mujoco_teleop"][0]
    try:
        obs, _ = vec.reset(seed=[EVAL_SEEDS[0]])
        batch = preprocess_observation(obs)
        assert set(batch) == {k for k in policy if k != "action"}
        assert vec.call("_max_episode_steps") == (4,) and vec.call("task") == (TASK,)
        assert vec.unwrapped.metadata["render_fps"] == EVAL_HZ and isinstance(vec.unwrapped.metadata["render_fps"], int)  # PyAV's rate
        done = False
        for _ in range(4):
            obs, _, terminated, truncated, info = vec.step(np.zeros((1, *vec.single_action_space.shape), np.float32))
            done = bool(terminated[0] or truncated[0])
            assert "is_success" in info
        assert done  # the TimeLimit ended it
    finally:
        vec.close()


# -- the browser page as a LeRobot teleoperator -----------------------------------------------------------------------


def test_the_pages_gizmo_gives_so101_follower_joint_targets_through_ik():
    """`mujoco_teleop_web` keyed like so101_follower (degrees, gripper 0..100); the page is served; a gizmo target
    (what the page's gizmo sends) 4 cm lower moves the joint targets, and the IK's targets put the EE there."""
    import urllib.request

    import mujoco

    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.teleoperators import TeleoperatorConfig, make_teleoperator_from_config

    from tests.support import wait_until

    teleoperator = make_teleoperator_from_config(TeleoperatorConfig.get_choice_class("mujoco_teleop_web")(robot="so101"))
    assert list(teleoperator.action_features) == SO101_KEYS
    teleoperator.connect()
    try:
        assert urllib.request.urlopen(teleoperator.url, timeout=60).status == 200
        home = teleoperator.get_action()
        assert list(home) == SO101_KEYS and 0.0 <= home["gripper.pos"] <= 100.0
        controller = teleoperator.env.session.controller
        pos, quat = controller.ee_pose(0)
        goal = pos + np.array([0.0, 0.0, -0.04])
        teleoperator.app.gizmo.push(0, goal, quat)
        wait_until(lambda: controller.data.time > 1.0, timeout_s=120, what="a simulated second on the page's thread")
        moved = teleoperator.get_action()
        assert max(abs(moved[k] - home[k]) for k in SO101_KEYS[:5]) > 1.0  # degrees
        # the targets, as joint angles, put the EE at the gizmo's goal (forward kinematics of the model)
        model = teleoperator.env.model
        data = mujoco.MjData(model)
        for key, joint in zip(SO101_KEYS[:5], teleoperator.env.arms[0].joints):
            data.qpos[model.joint(joint).qposadr[0]] = math.radians(moved[key])
        mujoco.mj_kinematics(model, data)
        assert np.linalg.norm(data.site_xpos[teleoperator.env.arms[0].site_id] - goal) < 0.01
    finally:
        teleoperator.disconnect()


def test_ee_delta_actions_move_the_hand_by_ee_step_m_through_ik():
    """`action_space=ee_delta` takes keyboard_ee's / gamepad's action (delta_x/y/z -1..1, gripper 0 close, 1 keep,
    2 open): 20 ticks of delta_z = +1 at 5 mm a unit raise the hand's target 10 cm and the hand follows; 0 closes."""
    import teleop.lerobot_plugin  # noqa: F401
    from lerobot.robots import RobotConfig, make_robot_from_config

    config = RobotConfig.get_choice_class("mujoco_teleop")(robot="so101", cameras="", action_space="ee_delta", ee_step_m=0.005)
    robot = make_robot_from_config(config)
    assert list(robot.action_features) == ["delta_x", "delta_y", "delta_z", "gripper"] and robot.cameras == {}
    keep = {"delta_x": 0.0, "delta_y": 0.0, "delta_z": 0.0, "gripper": 1.0}
    robot.connect()
    try:
        controller = robot.env.session.controller
        for _ in range(15):
            robot.send_action({**keep, "gripper": 2.0})  # open
        opened = robot.get_observation()["gripper.pos"]
        start, target = controller.ee_pose(0)[0].copy(), controller.target_pose(0)[0].copy()
        for _ in range(20):
            robot.get_observation()
            sent = robot.send_action({**keep, "delta_z": 1.0, "gripper": 0.0})
        assert sent == {**keep, "delta_z": 1.0, "gripper": 0.0}
        assert np.allclose(controller.target_pose(0)[0] - target, [0.0, 0.0, 0.1], atol=1e-9)
        for _ in range(15):  # the arm settles on its last target
            robot.send_action(keep)
        moved = controller.ee_pose(0)[0] - start
        assert 0.08 < moved[2] < 0.11 and np.hypot(moved[0], moved[1]) < 0.01
        assert opened > 90 and robot.get_observation()["gripper.pos"] < 10  # open, then closed (0..100)
        with pytest.raises(ValueError, match="delta_y"):
            robot.send_action({"delta_x": 0.0, "delta_z": 0.0})
    finally:
        robot.disconnect()
