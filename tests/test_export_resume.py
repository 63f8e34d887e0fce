"""An export killed with SIGKILL resumes with `--resume` into the dataset an uninterrupted export makes.

Real processes and signals: `teleop export` runs as a child, is killed with kill -9 at a
random moment after its first finalized piece, refuses a plain re-run, and `--resume`
finishes it. The result is compared with an export that was never interrupted: frames,
values, images, features, statistics and episode order.
"""

from __future__ import annotations

import json
import os
import random
import shutil
import signal
import time
from pathlib import Path

import numpy as np
import pytest

import teleop
from replay.export.pieces import journal_dir
from tests.support import popen_cli, run_cli

pytestmark = pytest.mark.e2e
ROOT = Path(__file__).resolve().parent.parent
# PNG frames (--no-video): H.264 output is not byte-reproducible between two runs on a loaded machine
# (the decoded frames differ by codec noise), so a byte-for-byte comparison needs images stored as they are.
EXPORT = ["--repo-id", "test/resume", "--cameras", "front", "--image-size", "64x48", "--piece-episodes", "2", "--no-video"]


@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> Path:
    """Seven scripted picks at 15 Hz (~72 frames each): four pieces of two to kill an export between."""
    out = tmp_path_factory.mktemp("episodes")
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=15)
    with teleop.Recorder(session, out, formats=("mcap",), verify="off"):
        for seed in range(7):
            session.reset(seed)
            teleop.run_episode(session, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")])
    assert len(list(out.glob("*.mcap"))) == 7
    return out


@pytest.fixture(scope="module")
def whole(episodes, tmp_path_factory) -> Path:
    """The serial export never interrupted: the reference a resumed one must equal, and a finished dataset."""
    out = tmp_path_factory.mktemp("whole") / "ds"
    done = _export(episodes, out)
    assert done.returncode == 0, done.stderr[-2000:]
    assert not journal_dir(out).exists()
    return out


@pytest.fixture(scope="module")
def whole_frames(whole) -> tuple[dict, list[dict]]:
    """The uninterrupted dataset's info and every frame, read once for the tests that compare with it."""
    return _frames(whole)


def _export(src: Path, out: Path, *extra: str):
    return run_cli("export", str(src), "--out", str(out), *EXPORT, *extra, env={"HF_HUB_OFFLINE": "1"}, timeout=600)


def _start_export(src: Path, out: Path, log: Path, *extra: str):
    """`teleop export` started in its own process (as run_cli: forked from the warm process when it may be), its
    output in `log`; a Popen, or what the tests use of one (pid, poll, wait)."""
    with open(log, "w") as stream:
        return popen_cli(["export", str(src), "--out", str(out), *EXPORT, *extra], stream, env={"HF_HUB_OFFLINE": "1"})


def _frames(root: Path) -> tuple[dict, list[dict]]:
    from lerobot.datasets import LeRobotDataset

    ds = LeRobotDataset("test/resume", root=root)
    rows = []
    for i in range(len(ds)):
        item = ds[i]
        rows.append({k: (v.numpy() if hasattr(v, "numpy") else v) for k, v in item.items()})
    return ds.meta.info, rows


def test_a_killed_export_resumes_into_the_uninterrupted_dataset(episodes, whole, whole_frames, tmp_path):
    out, log = tmp_path / "killed", tmp_path / "export.log"
    proc = _start_export(episodes, out, log)
    manifest = journal_dir(out) / "manifest.json"
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:
        if manifest.is_file() and json.loads(manifest.read_text())["done"] >= 2:
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the export ended before it could be killed: " + log.read_text()[-2000:]
    time.sleep(random.uniform(0.0, 0.4))  # somewhere in the next piece (or between pieces)
    assert proc.poll() is None, "the export ended before it could be killed"
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    done = json.loads(manifest.read_text())["done"]
    assert 2 <= done < 7

    again = _export(episodes, out)
    assert again.returncode == 2 and "--resume" in again.stderr and "Traceback" not in again.stderr
    assert len(again.stderr.strip().splitlines()) == 1

    resumed = _export(episodes, out, "--resume")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert f"{done} of 7 episodes were exported" in resumed.stderr
    assert not journal_dir(out).exists()

    info_a, rows_a = whole_frames
    info_b, rows_b = _frames(out)
    assert info_a["features"] == info_b["features"]
    assert (info_a["total_episodes"], info_a["total_frames"]) == (info_b["total_episodes"], info_b["total_frames"]) == (7, len(rows_a))
    for a, b in zip(rows_a, rows_b, strict=True):
        assert a.keys() == b.keys()
        for key in a:
            if isinstance(a[key], np.ndarray):
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            else:
                assert a[key] == b[key], key
    stats_a = json.loads((whole / "meta" / "stats.json").read_text())
    stats_b = json.loads((out / "meta" / "stats.json").read_text())
    assert stats_a == stats_b


def test_resume_refuses_other_options_and_a_finished_dataset(episodes, whole, tmp_path):
    out = tmp_path / "ds"
    shutil.copytree(whole, out)  # a finished export (the reference's copy: this test changes it)
    again = _export(episodes, out, "--resume")
    assert again.returncode == 2 and "no interrupted export" in again.stderr
    # an interrupted one, faked by a journal of a run with other options
    journal_dir(out).mkdir()
    (journal_dir(out) / "manifest.json").write_text(json.dumps({
        "format": 1, "episodes": [str(p.resolve()) for p in sorted(episodes.glob("*.mcap"))],
        "options": {"repo_id": "test/resume", "action": "ee_pose"}, "done": 2, "files": {}, "snapshot": "meta_snapshot.2"}))
    other = _export(episodes, out, "--resume")
    assert other.returncode == 2 and "other options" in other.stderr and "Traceback" not in other.stderr


def test_a_killed_parallel_export_resumes_into_the_uninterrupted_dataset(episodes, whole, whole_frames, tmp_path):
    """`--workers 2`: shards in `.NAME.parts/` beside the dataset; after kill -9 the whole shards are kept,
    a shard cut short continues from its last whole piece, and the merge gives the uninterrupted dataset (the
    serial one: a parallel export equals it, test_export_parallel.py, its statistics merged from the shards')."""
    from replay.export.shards import parts_dir

    out, log = tmp_path / "killed", tmp_path / "export.log"
    proc = _start_export(episodes, out, log, "--workers", "2")
    parts = parts_dir(out)
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and proc.poll() is None:  # a shard has a whole piece
        if any(json.loads(m.read_text())["done"] >= 2 for m in parts.glob(".shard_*.export/manifest.json")
               if m.stat().st_size):
            break
        time.sleep(0.05)
    assert proc.poll() is None, "the export ended before it could be killed: " + log.read_text()[-2000:]
    os.kill(proc.pid, signal.SIGKILL)
    assert proc.wait(timeout=30) == -signal.SIGKILL
    time.sleep(1.0)  # the workers see their parent gone and exit
    assert (parts / "plan.json").is_file()

    again = _export(episodes, out, "--workers", "2")
    assert again.returncode == 2 and "--resume" in again.stderr and "Traceback" not in again.stderr

    resumed = _export(episodes, out, "--workers", "2", "--resume")
    assert resumed.returncode == 0, resumed.stderr[-2000:]
    assert "resuming" in resumed.stderr and not parts.exists()
    info_a, rows_a = whole_frames
    info_b, rows_b = _frames(out)
    assert info_a["features"] == info_b["features"] and len(rows_a) == len(rows_b)
    for a, b in zip(rows_a, rows_b, strict=True):
        for key in a:
            if isinstance(a[key], np.ndarray):
                np.testing.assert_array_equal(a[key], b[key], err_msg=key)
            else:
                assert a[key] == b[key], key
    stats_a = json.loads((whole / "meta" / "stats.json").read_text())
    stats_b = json.loads((out / "meta" / "stats.json").read_text())
    assert stats_a.keys() == stats_b.keys()
    bad = []
    for feature, stats in stats_a.items():  # merged from the shards': the serial figures up to float rounding
        assert stats.keys() == stats_b[feature].keys(), feature
        for name, value in stats.items():
            if not np.allclose(np.asarray(stats_b[feature][name], float), np.asarray(value, float), rtol=1e-5, atol=1e-6):
                bad.append((feature, name, value, stats_b[feature][name]))
    assert not bad, bad
