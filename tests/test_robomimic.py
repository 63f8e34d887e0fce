"""Our HDF5 episodes open in robomimic 0.3's own SequenceDataset, next_obs included, and
say each fact once (env_args: the environment; the demo attrs: the final outcome)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import h5py
import mujoco
import numpy as np
import pytest

from replay import load_episode, resimulate
from tests.support import PICK, record_script, run_json

OBS_KEYS = ("qpos", "qvel", "ee_pose", "ee_target", "gripper")
OUTCOME = {"success", "complete", "steps"}
PER_EPISODE = OUTCOME | {"start_time", "episode_index", "wall_time", "teleop_version", "platform", "python_version"}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[str, Path]:
    """A successful scripted lift, recorded to both formats; the MCAP also converted to HDF5."""
    directory = tmp_path_factory.mktemp("robomimic")
    out = record_script(directory, PICK, "--format", "both", "--no-verify")
    assert out["success"] is True
    paths = {Path(p).suffix[1:]: Path(p) for p in out["files"]}
    converted = directory / "converted.hdf5"
    run_json("convert", str(paths["mcap"]), "--to", "hdf5", str(converted), "--json")
    return {**paths, "converted": converted}


def _dataset(path: Path):
    """robomimic's SequenceDataset on `path`. robomimic 0.3.0 is installed by `./run.sh test` (pip --no-deps: its
    egl_probe dependency needs a compiler); imported here, not at collection, where torch cost every worker seconds."""
    import robomimic.utils.obs_utils as ObsUtils
    from robomimic.utils.dataset import SequenceDataset

    ObsUtils.initialize_obs_modality_mapping_from_dict({"low_dim": list(OBS_KEYS)})
    return SequenceDataset(hdf5_path=str(path), obs_keys=OBS_KEYS, dataset_keys=("actions", "rewards", "dones"),
                           load_next_obs=True, hdf5_cache_mode="low_dim")


@pytest.mark.parametrize("which", ["hdf5", "converted"])
def test_robomimic_sequence_dataset_reads_obs_and_next_obs(recorded, which):
    path = recorded[which]
    dataset = _dataset(path)
    try:
        with h5py.File(path, "r") as f:
            demo = f["data/demo_0"]
            T = int(demo.attrs["num_samples"])
            assert len(dataset) == T > 10
            for t in (0, T // 2, T - 1):
                item = dataset[t]
                # robomimic gives (seq_length, n) arrays: obs as stored (float64), actions as float32.
                for key in OBS_KEYS:
                    np.testing.assert_array_equal(item["obs"][key], demo[f"obs/{key}"][t : t + 1])
                    np.testing.assert_array_equal(item["next_obs"][key], demo[f"next_obs/{key}"][t : t + 1])
                np.testing.assert_array_equal(item["actions"], demo["actions"][t : t + 1].astype(np.float32))
            for key in OBS_KEYS:
                obs, nxt = demo[f"obs/{key}"][()], demo[f"next_obs/{key}"][()]
                assert obs.shape == nxt.shape and obs.shape[0] == T
                np.testing.assert_array_equal(nxt[:-1], obs[1:])  # next_obs is obs one step on
            # obs[t] is what was seen before action t: the pose the previous step reached,
            # next_obs[t] the pose step t reached (the recorded row).
            np.testing.assert_array_equal(demo["next_obs/ee_pose"][()], demo["ee_pose"][:, 0])
            assert not np.array_equal(demo["obs/ee_pose"][0], demo["ee_pose"][0, 0])
    finally:
        dataset.close_and_delete_hdf5_handle()


def test_last_next_obs_is_the_state_after_the_last_step(recorded):
    """Checked against a full re-simulation from state 0, which ends in the state after the last step."""
    ep = load_episode(recorded["hdf5"])
    model = ep.build_model()
    data = mujoco.MjData(model)
    assert resimulate(ep, model=model, data=data, warn=False).bit_exact
    with h5py.File(recorded["hdf5"], "r") as f, h5py.File(recorded["converted"], "r") as g:
        demo = f["data/demo_0"]
        assert demo.attrs["next_obs_final"] == "simulated"
        assert np.array_equal(demo["next_obs/qpos"][-1], data.qpos) and np.array_equal(demo["next_obs/qvel"][-1], data.qvel)
        assert not np.array_equal(demo["next_obs/qpos"][-1], demo["obs/qpos"][-1])  # the arm still moved
        for key in OBS_KEYS:  # `teleop convert` writes the same pairs as the recorder
            assert np.array_equal(g[f"data/demo_0/next_obs/{key}"][()], demo[f"next_obs/{key}"][()]), key
            assert np.array_equal(g[f"data/demo_0/obs/{key}"][()], demo[f"obs/{key}"][()]), key


@pytest.mark.parametrize("which", ["hdf5", "converted"])
def test_each_fact_once_with_its_final_value(recorded, which):
    with h5py.File(recorded[which], "r") as f:
        env_args = json.loads(f["data"].attrs["env_args"])
        assert set(env_args) == {"env_name", "type", "env_kwargs"} and env_args["env_name"] == "lift"
        kwargs = env_args["env_kwargs"]
        assert not PER_EPISODE & kwargs.keys(), PER_EPISODE & kwargs.keys()
        assert kwargs["robot"] == "panda" and kwargs["control_hz"] == 30.0 and kwargs["robot_spec"]["arms"]
        demo = f["data/demo_0"]
        assert bool(demo.attrs["success"]) is True and bool(demo.attrs["complete"]) is True
        assert bool(demo.attrs["closed"]) is True
        assert int(demo.attrs["num_samples"]) == int(f["data"].attrs["total"]) == demo["actions"].shape[0]
        teleop_meta = json.loads(demo.attrs["teleop_meta"])
        assert not OUTCOME & teleop_meta.keys()
    ep = load_episode(recorded[which])
    assert ep.meta.success is True and ep.meta.complete is True and ep.meta.outcome.steps == ep.steps
    mcap = load_episode(recorded["mcap"]).meta
    assert mcap.replace(outcome=ep.meta.outcome) == ep.meta  # the reader gets the same metadata from both files


def test_schema_1_files_still_load_and_replay(recorded, tmp_path):
    """A file laid out as before (outcome copied into teleop_meta and env_args, no next_obs) reads the same."""
    old = tmp_path / "old.hdf5"
    shutil.copy(recorded["hdf5"], old)
    with h5py.File(old, "r+") as f:
        demo = f["data/demo_0"]
        meta = json.loads(demo.attrs["teleop_meta"])
        meta.update(schema_version=1, success=False, complete=False)
        f["data"].attrs["env_args"] = json.dumps({"env_name": "lift", "type": 0, "env_kwargs": meta, "source": "teleop"})
        meta.update(success=True, complete=True, steps=int(demo.attrs["num_samples"]))
        demo.attrs["teleop_meta"] = json.dumps(meta)
        del demo["next_obs"], demo.attrs["next_obs_final"]
    ep = load_episode(old)
    assert ep.meta.success is True and ep.meta.complete is True and not ep.truncated
    assert np.array_equal(ep.state, load_episode(recorded["hdf5"]).state)
    assert resimulate(ep, warn=False).bit_exact


def test_last_next_obs_is_repeated_when_the_replay_does_not_reproduce_the_recording(recorded, tmp_path):
    """A recording this machine does not reproduce (here: its last state nudged) gets no invented final state."""
    from replay.convert import write_episode

    ep = load_episode(recorded["hdf5"])
    ep.state[-1, 1] += 1e-9  # qpos[0] of the last state (state = time, qpos, qvel, ...)
    ep.qpos[-1, 0] += 1e-9
    out = write_episode(ep, tmp_path / "nudged.hdf5", "hdf5")
    with h5py.File(out, "r") as f:
        demo = f["data/demo_0"]
        assert demo.attrs["next_obs_final"] == "repeated"
        np.testing.assert_array_equal(demo["next_obs/qpos"][-1], demo["obs/qpos"][-1])
        np.testing.assert_array_equal(demo["next_obs/qpos"][:-1], demo["obs/qpos"][1:])


@pytest.mark.parametrize("steps", [0, 1])
def test_episodes_too_short_to_check_still_load(tmp_path, steps):
    from tests.support import record_pusher_episode

    paths = record_pusher_episode(tmp_path, 0, steps=steps, formats=("hdf5",))
    ep = load_episode(paths[0])
    assert ep.steps == steps and ep.meta.success is True and ep.meta.outcome.steps == steps
    with h5py.File(paths[0], "r") as f:
        demo = f["data/demo_0"]
        assert demo.attrs["next_obs_final"] == "repeated"  # no recorded transition to check a replay on
        for key in OBS_KEYS:
            assert demo[f"next_obs/{key}"].shape == demo[f"obs/{key}"].shape and len(demo[f"obs/{key}"]) == steps
