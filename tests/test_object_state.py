"""Object state as an observation (`observation.environment_state`) and why eval rollouts fail.

Real parts: a scripted recording exported through LeRobot and read back with
LeRobotDataset, the Gymnasium env driven by a policy that sees the cube only
through the environment state, and `teleop eval`'s rollouts judged by the
annotate rules.
"""

from __future__ import annotations

import json
from pathlib import Path

import mujoco
import numpy as np
import pytest

import teleop
from replay.features import ENV_STATE
from teleop.learn.evaluate import EvalOptions, evaluate
from teleop.learn.gym_env import TeleopEnv
from teleop.learn.policy import ScriptedPolicy
from tests.support import run_cli

ROOT = Path(__file__).resolve().parent.parent
SCRIPTS = ROOT / "scenes" / "scripts"


def _base_frame(data: mujoco.MjData, base: int, body: int) -> np.ndarray:
    """A body's position and wxyz quaternion in the base body's frame, computed independently of the export."""
    rot = data.xmat[base].reshape(3, 3)
    pos = rot.T @ (data.xpos[body] - data.xpos[base])
    rel = rot.T @ data.xmat[body].reshape(3, 3)
    quat = np.empty(4)
    mujoco.mju_mat2Quat(quat, rel.reshape(-1))
    return np.concatenate([pos, quat if quat[0] >= 0 else -quat])


@pytest.fixture(scope="module")
def lift_episode(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("rec")
    session = teleop.Session(scene="lift", robot="panda", seed=3, control_hz=30)
    with teleop.Recorder(session, out, formats=("mcap",)) as rec:
        result = teleop.run_episode(session, [teleop.ScriptDevice(SCRIPTS / "lift_pick.json")])
    assert result.success
    return rec.paths[0]


def _export(episode: Path, out: Path, *extra: str) -> None:
    proc = run_cli("export", str(episode), "--out", str(out), "--repo-id", "local/os", "--cameras", "none", *extra)
    assert proc.returncode == 0, proc.stderr[-2000:]


def test_export_writes_the_objects_pose_in_the_robot_base_frame(lift_episode, tmp_path):
    from lerobot.datasets import LeRobotDataset

    _export(lift_episode, tmp_path / "ds")
    ds = LeRobotDataset("local/os", root=tmp_path / "ds")
    feature = ds.meta.features[ENV_STATE]
    assert feature["names"] == ["cube.x", "cube.y", "cube.z", "cube.qw", "cube.qx", "cube.qy", "cube.qz"]
    episode = teleop.load_episode(lift_episode)
    model = episode.build_model()
    base, cube = model.body("link0").id, model.body("cube").id
    expected = {k: _base_frame(data, base, cube) for k, data in teleop.replay_states(episode, model)}
    for k in (0, len(expected) // 2, len(expected) - 1):
        got = np.asarray(ds[k][ENV_STATE], dtype=np.float64)
        np.testing.assert_allclose(got, expected[k], atol=1e-5)
    # the cube was lifted: its height above the base grows along the episode
    assert float(ds[len(expected) - 1][ENV_STATE][2]) > float(ds[0][ENV_STATE][2]) + 0.04


def test_a_fixed_object_placed_per_seed_is_in_the_state():
    """pick_place's bin has no joint but stands left or right by seed: a policy must see where."""
    seen = []
    for seed in (0, 1, 2, 3):
        env = TeleopEnv("pick_place", "panda", cameras=())
        try:
            obs, _ = env.reset(seed=seed)
            assert env.objects is not None and env.objects.names == ["cube", "bin"]
            bin_state = np.asarray(obs[ENV_STATE][7:], dtype=np.float64)
            model, data = env.session.controller.model, env.session.controller.data
            expected = _base_frame(data, model.body("link0").id, model.body("bin").id)
            np.testing.assert_allclose(bin_state, expected, atol=1e-5)
            seen.append(bin_state[:3])
        finally:
            env.close()
    assert max(abs(a[1] - b[1]) for a in seen for b in seen) > 0.1  # both sides of the cube's area occur


def test_no_object_state_leaves_the_feature_out(lift_episode, tmp_path):
    _export(lift_episode, tmp_path / "ds", "--no-object-state")
    info = json.loads((tmp_path / "ds" / "meta" / "info.json").read_text())
    assert ENV_STATE not in info["features"] and "observation.state" in info["features"]


class CubeFromEnvState:
    """Lifts the cube knowing it only from `observation.environment_state` (ee_pose actions)."""

    def __init__(self, env: TeleopEnv) -> None:
        self.env = env
        self.phase, self.wait = 0, 0

    def _world(self, obs) -> np.ndarray:
        data, base = self.env.data, self.env.objects.base_id
        local = np.asarray(obs[ENV_STATE][:3], dtype=np.float64)
        return data.xpos[base] + data.xmat[base].reshape(3, 3) @ local

    def __call__(self, obs) -> np.ndarray:
        cube = self._world(obs)
        ee = np.asarray(obs["observation.ee_pose"], dtype=np.float64)
        quat = ee[3:7]
        goals = [cube + [0, 0, 0.12], cube + [0, 0, 0.0], cube, cube + [0, 0, 0.2]]
        goal = goals[self.phase]
        if self.phase in (0, 1) and np.linalg.norm(ee[:3] - goal) < 0.01:
            self.phase += 1
        elif self.phase == 2:
            self.wait += 1
            if self.wait > 15:
                self.phase = 3
        gripper = 1.0 if self.phase < 2 else 0.0
        step = goal - ee[:3]
        step *= min(1.0, 0.02 / max(np.linalg.norm(step), 1e-9))  # at most 2 cm a tick toward the goal
        return np.concatenate([ee[:3] + step, quat, [gripper]])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_policy_reading_the_environment_state_lifts_the_cube(seed):
    env = TeleopEnv("lift", "panda", cameras=(), action="ee_pose", max_seconds=8.0)
    try:
        obs, _ = env.reset(seed=seed)
        assert env.observation_space.contains(obs)
        policy = CubeFromEnvState(env)
        for _ in range(env.max_steps):
            obs, _, terminated, truncated, info = env.step(policy(obs))
            if terminated or truncated:
                break
        assert info["is_success"], f"seed {seed}: phase {policy.phase}"
    finally:
        env.close()


def _script(tmp_path: Path, name: str, steps: list[dict]) -> Path:
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps({"steps": steps}))
    return path


def test_eval_names_how_far_each_failed_rollout_got(tmp_path):
    """Rollouts that fail in known ways: never going to the cube, holding it over the bin without
    opening, and the whole task (a success that reached both subtasks)."""
    approach = [
        {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
        {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 1.0, "move": [0, 0, 0.15]},
        {"duration": 1.5, "to_body": "bin", "offset": [0, 0, 0.16]},
    ]
    cases = {
        "wander": ([{"duration": 3.0, "move": [0, 0.05, 0.05], "gripper": "open"}], "never_grasped", []),
        "hold": (approach + [{"duration": 2.0}], "not_placed", ["grasp cube"]),
    }
    for name, (steps, reason, reached) in cases.items():
        policy = ScriptedPolicy(_script(tmp_path, name, steps))
        summary = evaluate(policy, EvalOptions(scene="pick_place", robot="panda", episodes=1, seed=0,
                                               action="ee_pose", cameras=(), max_seconds=6.0))
        (outcome,) = summary.per_episode
        assert not outcome.success
        assert (outcome.failure, outcome.reached) == (reason, reached), name
        assert summary.to_json()["failure_breakdown"] == {reason: 1}
    full = ScriptedPolicy(SCRIPTS / "pick_place.json")
    summary = evaluate(full, EvalOptions(scene="pick_place", robot="panda", episodes=1, seed=0, action="ee_pose",
                                         cameras=(), max_seconds=10.0))
    (outcome,) = summary.per_episode
    assert outcome.success and outcome.failure is None and outcome.reached == ["grasp cube", "place bin"]
    assert summary.to_json()["failure_breakdown"] == {}


def test_lift_that_grasps_but_never_lifts_times_out(tmp_path):
    steps = [
        {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
        {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 1.5},
    ]
    summary = evaluate(ScriptedPolicy(_script(tmp_path, "grip", steps)),
                       EvalOptions(scene="lift", robot="panda", episodes=1, seed=0, action="ee_pose", cameras=(),
                                   max_seconds=4.5))
    (outcome,) = summary.per_episode
    assert (outcome.success, outcome.failure, outcome.reached) == (False, "timeout", ["grasp cube"])
