"""teleop.gym: Gymnasium environments that observe and act as the LeRobot export records.

Real MuJoCo, real rendering, Gymnasium's own checker; the export comparison
records an episode with the CLI and exports it through LeRobot.
"""

from __future__ import annotations

from collections.abc import Callable

import gymnasium
import numpy as np
import pytest

import teleop.gym as tg
from devices.script import ScriptDevice
from replay import load_episode
from scenes import SceneError
from scenes.errors import TeleopError
from teleop.errors import EnvError
from tests.support import ROOT, SMALL, checked, make_robot, run_cli

LIFT_SCRIPT = ROOT / "scenes" / "scripts" / "lift_pick.json"
def test_every_builtin_scene_and_robot_pair_is_registered():
    expected = {f"teleop/{s}-{r}-v0" for r in ("panda", "ur5e", "so101") for s in ("lift", "stack", "pick_place", "door")}
    expected |= {"teleop/lift-bimanual-v0", "teleop/handover-bimanual-v0"}
    assert set(tg.ENV_IDS) == expected
    assert all(i in gymnasium.registry for i in tg.ENV_IDS)
    assert tg.register_builtin() == tg.ENV_IDS  # importing or registering again changes nothing


MY_TASK = """name = "my_cube"
instruction = "Lift the small cube."
robots = ["panda", "so101"]
success = "lifted(cube, 0.05)"

[[object]]
name = "cube"
box = [0.02, 0.02, 0.02]
region = {x = [-0.05, 0.05], y = [-0.05, 0.05]}
"""


def test_a_task_file_registers_its_own_ids_that_pass_check_env(tmp_path):
    """Issue 38 item 8: `gymnasium.make("teleop/<file task>-panda-v0")` works once the file is registered."""
    path = tmp_path / "my_cube.toml"
    path.write_text(MY_TASK)
    with pytest.raises(gymnasium.error.NameNotFound):
        gymnasium.make("teleop/my_cube-panda-v0")
    ids = tg.register(path)
    assert ids == ["teleop/my_cube-panda-v0", "teleop/my_cube-so101-v0"]  # one per robot the file names
    assert tg.register(path) == ids  # again: nothing changes
    env = gymnasium.make(ids[0], image_size=SMALL)
    try:
        checked(env.unwrapped)
        assert env.unwrapped.session.scene_name == "my_cube"
    finally:
        env.close()
    clash = tmp_path / "copy.toml"  # another file of the same name would take its ids: refused in one line
    clash.write_text(MY_TASK)
    with pytest.raises(TeleopError, match="copy.toml: name: teleop/my_cube-panda-v0 is already"):
        tg.register(clash)
    with pytest.raises(TeleopError, match="no such task file"):
        tg.register(tmp_path / "missing.toml")


@pytest.mark.parametrize("env_id", tg.ENV_IDS)
def test_check_env_passes(env_id):
    env = gymnasium.make(env_id, image_size=SMALL)
    try:
        checked(env.unwrapped)  # with the render and close checks: they remake it from its spec
    finally:
        env.close()


@pytest.mark.parametrize("action", ["ee_pose", "ee_delta"])
def test_check_env_passes_for_ee_actions(action):
    env = gymnasium.make("teleop/lift-bimanual-v0", image_size=SMALL, action=action, cameras=("front",))
    try:
        checked(env.unwrapped)
        names = env.unwrapped.features["action"]["names"]
        assert env.unwrapped.action_space.shape == (len(names),) == (16 if action == "ee_pose" else 14,)
    finally:
        env.close()


def test_spaces_are_the_exports_features():
    env = tg.make_env("lift", "panda", image_size=(40, 24), cameras=("front", "wrist"), action="ee_pose")
    try:
        obs, info = env.reset(seed=4)
        space = env.observation_space
        assert set(obs) == {"observation.state", "observation.ee_pose", "observation.environment_state",
                            "observation.images.front", "observation.images.wrist"}
        assert env.features["observation.environment_state"]["names"][:3] == ["cube.x", "cube.y", "cube.z"]
        assert obs["observation.images.front"].shape == (24, 40, 3) and obs["observation.images.front"].dtype == np.uint8
        assert obs["observation.state"].dtype == np.float32 and obs["observation.state"].shape == (8,)
        for key, ft in env.features.items():
            box = env.action_space if key == "action" else space[key]
            assert box.shape == tuple(ft["shape"]) and str(box.dtype) == {"image": "uint8"}.get(ft["dtype"], ft["dtype"])
        assert env.features["action"]["names"] == ["x", "y", "z", "qw", "qx", "qy", "qz", "gripper"]
        assert info == {"is_success": False, "seed": 4, "time": 0.0}
        assert env.render() is None  # no render mode asked
    finally:
        env.close()


def test_cameras_none_observes_vectors_only_and_render_uses_the_front_camera():
    env = tg.make_env("door", "ur5e", cameras=(), image_size=SMALL, render_mode="rgb_array")
    try:
        obs, _ = env.reset()
        assert set(obs) == {"observation.state", "observation.ee_pose", "observation.environment_state"}
        assert obs["observation.environment_state"].shape == (14,)  # the frame's pose (placed per seed), the leaf's
        assert env.objects is not None and env.objects.names == ["door_frame", "door"]
        frame = env.render()
        assert frame.shape == (32, 32, 3) and frame.dtype == np.uint8 and frame.std() > 0
    finally:
        env.close()
        env.close()


def test_object_state_false_leaves_the_environment_state_out():
    env = tg.make_env("lift", "panda", cameras=(), object_state=False)
    try:
        obs, _ = env.reset(seed=0)
        assert set(obs) == {"observation.state", "observation.ee_pose"} and "observation.environment_state" not in env.features
    finally:
        env.close()


def test_a_robot_brought_by_toml(tmp_path):
    toml = make_robot(tmp_path / "robot")
    env = tg.make_env("lift", toml, cameras=("front",), image_size=SMALL, action="ee_delta")
    try:
        obs, _ = env.reset(seed=1)
        assert env.features["observation.state"]["names"][-1] == "gripper"
        obs, reward, terminated, truncated, info = env.step(np.array([0, 0, 0, 0, 0, 0, 1], np.float32))
        assert obs in env.observation_space and reward == 0.0 and not terminated and not truncated
    finally:
        env.close()


# -- the export's frames, the recorded episode ---------------------------------------


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A scripted lift episode recorded by the CLI and exported with PNG frames (exact pixels)."""
    from lerobot.datasets import LeRobotDataset  # the test command installs the lerobot extra: no skip

    from replay.export import ExportOptions
    from replay.export import export_dataset

    root = tmp_path_factory.mktemp("gym")
    result = run_cli("run", "--device", f"script:{LIFT_SCRIPT}", "--record", str(root / "rec"), "--seed", "3")
    assert result.returncode == 0, result.stderr
    out = root / "ds"
    options = ExportOptions(out=out, repo_id="local/gym", cameras=["front", "wrist"], image_size=SMALL, video=False, progress=False)
    export_dataset([root / "rec"], options, log=lambda line: None)
    frames = LeRobotDataset("local/gym", root=out, video_backend="pyav").hf_dataset.with_format(None)
    return load_episode(next((root / "rec").glob("*.mcap"))), frames


def assert_same_frame(obs: dict, frame: dict, k: int) -> None:
    for key in ("observation.state", "observation.ee_pose"):
        assert np.array_equal(obs[key], np.asarray(frame[key], np.float32)), f"{key} differs at frame {k}"
    for key in ("observation.images.front", "observation.images.wrist"):
        assert np.array_equal(obs[key], np.asarray(frame[key])), f"{key} differs at frame {k}"


def test_observations_equal_the_exported_frames_of_the_same_state(exported):
    episode, frames = exported
    env = tg.make_env("lift", "panda", control_hz=episode.meta.control_hz, image_size=SMALL)
    try:
        obs, _ = env.reset(seed=episode.meta.seed)
        assert np.array_equal(env.get_state(), episode.state[0])
        assert_same_frame(obs, frames[0], 0)
        for k in range(1, episode.steps, 7):
            assert_same_frame(env.set_state(episode.state[k]), frames[k], k)
    finally:
        env.close()


def test_joint_actions_from_recorded_ctrl_replay_the_episode_bit_for_bit(exported):
    episode, frames = exported
    env = tg.make_env("lift", "panda", control_hz=episode.meta.control_hz, image_size=SMALL, max_seconds=60)
    try:
        env.reset(seed=episode.meta.seed)
        arm = env.arms[0]
        for k in range(episode.steps):
            ctrl = episode.ctrl[k]
            action = np.array([*ctrl[arm.ctrl_ids], arm.gripper_fraction(ctrl[arm.gripper_id])])  # float64: exact
            obs, reward, terminated, truncated, info = env.step(action)
            if k + 1 < episode.steps:
                assert np.array_equal(env.get_state(), episode.state[k + 1]), f"state differs after step {k}"
                if k % 10 == 0:
                    assert_same_frame(obs, frames[k + 1], k + 1)
        assert info["is_success"] and terminated and reward == 1.0 and not truncated
        # The exported (float32) action column drives it to the same outcome.
        env.reset(seed=episode.meta.seed)
        outcomes = [env.step(np.asarray(frames[k]["action"], np.float32))[2] for k in range(episode.steps)]
        assert outcomes[-1]
    finally:
        env.close()


# -- a scripted policy, time limits, bad options -------------------------------------


def lift_policy(env: gymnasium.Env) -> Callable[[dict], np.ndarray]:
    """ee_pose actions that follow the lift script's targets (the script reads the scene, as a
    scripted policy may); returns act(obs) -> action."""
    session = env.unwrapped.session
    script = ScriptDevice(LIFT_SCRIPT)
    script.start()
    pos, quat = session.controller.target_pose(0)
    grip = [1.0]

    def act(obs) -> np.ndarray:
        nonlocal pos, quat
        for command in script.poll(session.controller, session.controller.dt):
            pos = command.target_pos if command.target_pos is not None else pos
            quat = command.target_quat if command.target_quat is not None else quat
            if command.gripper is not None:
                grip[0] = 1.0 if command.gripper == "open" else 0.0
        return np.array([*pos, *quat, grip[0]], dtype=np.float32)

    return act


@pytest.mark.parametrize("seed", [0, 5, 11])
def test_a_scripted_ee_pose_policy_lifts_the_cube(seed):
    env = gymnasium.make("teleop/lift-panda-v0", action="ee_pose", cameras=(), max_seconds=8)
    try:
        obs, info = env.reset(seed=seed)
        act = lift_policy(env)
        for _ in range(env.unwrapped.max_steps):
            obs, reward, terminated, truncated, info = env.step(act(obs))
            if terminated or truncated:
                break
        assert terminated and not truncated and reward == 1.0 and info["is_success"] and info["seed"] == seed
    finally:
        env.close()


def test_truncates_at_max_seconds_and_reset_without_seed_takes_the_next():
    env = tg.make_env("stack", "so101", control_hz=10, max_seconds=0.5, cameras=(), seed=7)
    try:
        obs, info = env.reset()
        assert info["seed"] == 7
        hold = obs["observation.state"].astype(np.float64)
        flags = [env.step(hold)[2:4] for _ in range(5)]
        assert flags == [(False, False)] * 4 + [(False, True)]
        assert env.unwrapped.session.controller.time == pytest.approx(0.5)
        assert env.reset()[1]["seed"] == 8 and env.reset(seed=2)[1]["seed"] == 2 and env.reset()[1]["seed"] == 3
    finally:
        env.close()


@pytest.mark.parametrize(
    "kwargs, kind, needle",
    [
        ({"scene": "nope"}, SceneError, "unknown scene 'nope'"),
        ({"robot": "nope"}, SceneError, "unknown robot 'nope'"),
        ({"scene": "handover"}, SceneError, "does not work with the single-arm robot"),
        ({"action": "torque"}, EnvError, "choose one of joint, ee_delta, ee_pose"),
        ({"cameras": ("nope",)}, EnvError, "unknown camera 'nope'"),
        ({"image_size": (0, 32)}, EnvError, "image size"),
        ({"max_seconds": 0}, EnvError, "max_seconds"),
        ({"seed": -1}, EnvError, "seed"),
        ({"control_hz": -5}, TeleopError, "control rate"),
        ({"render_mode": "human"}, EnvError, "render mode"),
    ],
)
def test_bad_options_raise_one_line_teleop_errors(kwargs, kind, needle):
    options = {"scene": "lift", "robot": "panda", "cameras": ()} | kwargs
    with pytest.raises(kind) as raised:
        tg.make_env(options.pop("scene"), options.pop("robot"), **options)
    assert isinstance(raised.value, TeleopError) and "\n" not in str(raised.value) and needle in str(raised.value)


def test_a_bad_action_raises_one_line():
    env = tg.make_env("lift", "panda", cameras=())
    try:
        env.reset()
        with pytest.raises(EnvError, match=r"action has shape \(3,\), expected \(8,\)"):
            env.step(np.zeros(3))
        with pytest.raises(EnvError, match="non-finite"):
            env.step(np.full(8, np.nan))
    finally:
        env.close()
