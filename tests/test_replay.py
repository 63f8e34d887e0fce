"""Replay: bit-exact in a fresh process, divergence is caught, state mode, convert,
recover, and every bad input ends as one line and exit code 2 with nothing overwritten."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import h5py
import mujoco
import numpy as np
import pytest
from mcap.reader import make_reader

from replay.convert import write_episode
from replay import EpisodeError, find_episodes, load_episode, replay_states, resimulate
from teleop.cli.entry import main
from tests.support import record_pusher_episode, run_cli, run_json

STEPS = 120


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> dict[str, Path]:
    directory = tmp_path_factory.mktemp("replay")
    paths = record_pusher_episode(directory, 0, steps=STEPS, formats=("mcap", "hdf5"), seed=1)
    return {p.suffix[1:]: p for p in paths}


def cli(capsys, *args: str) -> tuple[int, str, str]:
    """Run the CLI in this process (fast); a traceback would fail the test."""
    code = main(list(args))
    out, err = capsys.readouterr()
    return code, out, err


def assert_usage_error(capsys, *args: str, match: str) -> str:
    code, out, err = cli(capsys, *args)
    assert code == 2, (code, out, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("teleop ") and match in lines[0], err
    return lines[0]


@pytest.mark.parametrize("fmt", ["mcap", "hdf5"])
def test_bit_exact_replay_in_a_fresh_process(recorded, fmt):
    out = run_json("replay", str(recorded[fmt]), "--verify", "--json")
    assert out["bit_exact"] is True and out["first_divergence_step"] is None and out["max_abs_diff"] == 0.0
    assert out["steps"] == STEPS and out["compared"] == STEPS - 1 and out["mode"] == "action"


def test_divergence_is_found_and_fails_verify(recorded, tmp_path, capsys):
    ep = load_episode(recorded["mcap"])
    ctrl = ep.ctrl.copy()
    ctrl[60, 0] += 1e-9  # one nudge, far below anything visible
    nudged = dataclasses.replace(ep, ctrl=ctrl)
    result = resimulate(nudged)
    assert not result.bit_exact and result.first_divergence_step == 61 and 0 < result.max_abs_diff < 1e-3
    # robosuite-style state (time, qpos, qvel) without warmstart: detected as inexact, not hidden
    model = ep.build_model()
    from replay.engine import state_mask

    warm = state_mask(model, int(mujoco.mjtState.mjSTATE_WARMSTART))
    state = ep.state.copy()
    state[:, warm] = 0.0
    cold = resimulate(dataclasses.replace(ep, state=state))
    assert not cold.bit_exact and cold.first_divergence_step is not None

    path = tmp_path / "nudged.mcap"
    write_episode(nudged, path, "mcap")
    code, out, _ = cli(capsys, "replay", str(path), "--verify", "--json")
    assert code == 1 and json.loads(out)["first_divergence_step"] == 61


def test_state_mode_restores_every_state(recorded, capsys):
    ep = load_episode(recorded["hdf5"])
    seen = 0
    for k, data in replay_states(ep):
        assert np.array_equal(data.qpos, ep.qpos[k]) and data.time == ep.time[k]
        seen += 1
    assert seen == STEPS
    code, out, _ = cli(capsys, "replay", str(recorded["hdf5"]), "--json")
    assert code == 0 and json.loads(out)["mode"] == "state" and json.loads(out)["steps"] == STEPS


def test_inspect_json(recorded, capsys):
    code, out, _ = cli(capsys, "inspect", str(recorded["mcap"]), "--json")
    info = json.loads(out)
    for key in ("path", "format", "steps", "seconds", "success", "complete", "robot", "scene", "seed",
                "mujoco_version", "ee_tracking_error_mm"):
        assert key in info
    assert info["steps"] == STEPS and info["seconds"] == pytest.approx(STEPS * 0.05)
    assert info["seed"] == 1 and info["success"] is True and info["complete"] is True
    assert set(info["ee_tracking_error_mm"]) == {"median", "max"} and info["ee_tracking_error_mm"]["max"] >= 0


def test_convert_both_ways_keeps_everything(recorded, tmp_path, capsys):
    h5 = tmp_path / "a.hdf5"
    back = tmp_path / "b.mcap"
    assert cli(capsys, "convert", str(recorded["mcap"]), "--to", "hdf5", str(h5))[0] == 0
    assert cli(capsys, "convert", str(h5), "--to", "mcap", str(back))[0] == 0
    a, b = load_episode(recorded["mcap"]), load_episode(back)
    for name in ("time", "wall_time", "state", "ctrl", "ee_target", "ee_pose", "qpos", "qvel", "gripper"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert a.commands == b.commands and a.meta.success == b.meta.success and b.meta.complete
    assert resimulate(b).bit_exact
    assert find_episodes([tmp_path]) == [h5, back] and find_episodes([recorded["mcap"].parent])[0].suffix == ".mcap"


def _truncated_copy(src: Path, dst: Path) -> int:
    """Cut a finished MCAP in the middle of its last chunk, as a crash would; returns the cut."""
    with open(src, "rb") as fh:
        chunks = make_reader(fh).get_summary().chunk_indexes
    last = max(chunks, key=lambda c: c.chunk_start_offset)
    cut = last.chunk_start_offset + last.chunk_length // 2
    dst.write_bytes(src.read_bytes()[:cut])
    return cut


def test_truncated_mcap_inspect_recover_but_not_convert(recorded, tmp_path, capsys):
    src = tmp_path / "big.mcap"
    write_episode(load_episode(recorded["mcap"]), src, "mcap")  # several chunks
    cut = tmp_path / "cut.mcap"
    _truncated_copy(src, cut)
    code, out, _ = cli(capsys, "inspect", str(cut), "--json")
    info = json.loads(out)
    assert code == 0 and info["truncated"] is True and info["complete"] is False and 0 < info["steps"] < STEPS
    assert_usage_error(capsys, "convert", str(cut), "--to", "hdf5", str(tmp_path / "x.hdf5"), match="--recover")
    assert not (tmp_path / "x.hdf5").exists()
    fixed = tmp_path / "fixed.mcap"
    code, out, _ = cli(capsys, "inspect", str(cut), "--recover", str(fixed), "--json")
    assert code == 0 and json.loads(out)["recovered"]["steps"] == info["steps"]
    ep = load_episode(fixed)
    assert not ep.truncated and ep.steps == info["steps"] and resimulate(ep).bit_exact
    assert cli(capsys, "convert", str(fixed), "--to", "hdf5", str(tmp_path / "x.hdf5"))[0] == 0


def test_version_mismatch_warns(recorded, capsys):
    ep = load_episode(recorded["mcap"])
    old = dataclasses.replace(ep, meta=ep.meta.replace(mujoco_version="2.3.7", machine="arm64"))
    result = resimulate(old)
    err = capsys.readouterr().err.strip().splitlines()
    assert result.bit_exact and len(result.warnings) == 2
    assert len(err) == 2 and all("exactness is not promised" in line for line in err)


# -- bad input: one line, exit 2, nothing overwritten ---------------------------------


def test_missing_and_foreign_files(tmp_path, capsys):
    missing = tmp_path / "nope.mcap"
    for cmd in (["inspect", str(missing)], ["replay", str(missing), "--verify"],
                ["convert", str(missing), "--to", "hdf5", str(tmp_path / "o.hdf5")]):
        assert_usage_error(capsys, *cmd, match="no such file")
    text = tmp_path / "notes.mcap"
    text.write_text("just some text\n")
    assert_usage_error(capsys, "inspect", str(text), match="not an MCAP or HDF5 file")
    assert_usage_error(capsys, "replay", str(tmp_path), match="is a directory")
    empty = tmp_path / "empty.hdf5"
    empty.write_bytes(b"")
    assert_usage_error(capsys, "inspect", str(empty), match="file is empty")
    junk = tmp_path / "junk.mcap"
    junk.write_bytes(b"\x89MCAP0\r\n" + bytes(range(256)) * 4)
    assert_usage_error(capsys, "replay", str(junk), match="not a teleop episode")
    other = tmp_path / "other.hdf5"
    with h5py.File(other, "w") as f:
        f["x"] = np.arange(3)
    assert_usage_error(capsys, "inspect", str(other), match="missing group data/demo_0")
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["notes.mcap", "empty.hdf5", "junk.mcap", "other.hdf5"])


def test_hdf5_missing_dataset(recorded, tmp_path, capsys):
    path = tmp_path / "broken.hdf5"
    shutil.copy(recorded["hdf5"], path)
    with h5py.File(path, "a") as f:
        del f["data/demo_0/obs/qvel"]
    assert_usage_error(capsys, "replay", str(path), "--verify", match="missing dataset data/demo_0/obs/qvel")
    assert_usage_error(capsys, "inspect", str(path), match="missing dataset")


def test_wrong_state_size(recorded, tmp_path, capsys):
    path = tmp_path / "short_state.hdf5"
    shutil.copy(recorded["hdf5"], path)
    with h5py.File(path, "a") as f:
        states = f["data/demo_0/states"][()]
        del f["data/demo_0/states"]
        f["data/demo_0/states"] = states[:, :-1]
    assert_usage_error(capsys, "replay", str(path), match="states has")
    # consistent file, but the model needs a different state size
    ep = load_episode(recorded["mcap"])
    short = dataclasses.replace(ep, state=np.ascontiguousarray(ep.state[:, :-2]), meta=ep.meta.replace(nstate=ep.meta.nstate - 2))
    out = tmp_path / "short_state.mcap"
    write_episode(short, out, "mcap")
    assert_usage_error(capsys, "replay", str(out), "--verify", match="the recorded model needs")


def test_model_that_does_not_compile(recorded, tmp_path, capsys):
    ep = load_episode(recorded["mcap"])
    bad = dataclasses.replace(ep, meta=ep.meta.replace(model_xml="<mujoco><worldbody><geom type='nonsense'/></worldbody></mujoco>"))
    out = tmp_path / "bad_model.mcap"
    write_episode(bad, out, "mcap")
    assert_usage_error(capsys, "replay", str(out), "--verify", match="does not compile")
    assert_usage_error(capsys, "convert", str(out), "--to", "hdf5", str(tmp_path / "b.hdf5"), match="does not compile")
    assert not (tmp_path / "b.hdf5").exists()
    assert cli(capsys, "inspect", str(out), "--json")[0] == 0  # inspect does not need the model


def test_never_overwrites(recorded, tmp_path, capsys):
    taken = tmp_path / "taken.hdf5"
    taken.write_bytes(b"precious")
    assert_usage_error(capsys, "convert", str(recorded["mcap"]), "--to", "hdf5", str(taken), match="already exists")
    assert_usage_error(capsys, "inspect", str(recorded["mcap"]), "--recover", str(taken), match="already exists")
    assert taken.read_bytes() == b"precious"
    assert_usage_error(capsys, "convert", str(recorded["mcap"]), "--to", "mcap", str(tmp_path / "o.hdf5"), match="does not match")
    assert_usage_error(capsys, "inspect", str(recorded["hdf5"]), "--recover", str(tmp_path / "r.mcap"), match="MCAP files only")
    assert_usage_error(capsys, "replay", str(recorded["mcap"]), "--mode", "state", "--verify", match="--mode action")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["taken.hdf5"]


def test_one_line_errors_in_a_fresh_process(tmp_path):
    result = run_cli("replay", str(tmp_path / "missing.mcap"), "--verify")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert result.stderr.strip().splitlines() == [f"teleop replay: error: {tmp_path / 'missing.mcap'}: no such file"]


def test_load_episode_error_type(tmp_path):
    with pytest.raises(EpisodeError, match="no such file"):
        load_episode(tmp_path / "x.hdf5")
