"""`teleop export --drop-idle`: a person's pauses and the waits for a gripper left out of the dataset.

Real recordings (`teleop run --record` of a script that stops for a second half-way), real
LeRobot, real rendering with two cameras (one in the stream's thread, one in its render
worker, which must skip the same frames).
"""

from __future__ import annotations

import os

import numpy as np
import pytest

from tests.support import ROOT, record_script, run_cli, run_main, write_script

import lerobot  # noqa: E402,F401  (the test command installs the lerobot extra)
os.environ["HF_HUB_OFFLINE"] = "1"

from replay.export import export_dataset  # noqa: E402
from replay.export import ExportOptions  # noqa: E402
from replay.export.pieces import ResumeError  # noqa: E402
from replay.export.stream import IDLE_TOLERANCE, idle_mask  # noqa: E402

HZ = "15"
KEYS = ("action", "observation.state", "observation.environment_state")
CAMERAS = ("observation.images.front", "observation.images.wrist")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """Two picks (seeds 0, 1) that wait 1.2 s, hand still, half-way to the cube."""
    root = tmp_path_factory.mktemp("idle")
    script = write_script(root / "pause.json", [
        {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.08], "gripper": "open"},
        {"duration": 1.2},  # the pause
        {"duration": 0.8, "to_body": "cube", "offset": [0, 0, 0]},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 0.8, "move": [0, 0, 0.1]},
    ])
    out = record_script(root / "rec", script, "--control-hz", HZ, "--episodes", "2")
    assert all(e["success"] for e in out["per_episode"])
    return sorted((root / "rec").glob("*.mcap"))


def _opts(out, **kw) -> ExportOptions:
    return ExportOptions(out=out, repo_id="t/idle", cameras=["front", "wrist"], image_size=(32, 32), video=False,
                         progress=False, **kw)


@pytest.fixture(scope="module")
def dropped(recorded, tmp_path_factory):
    """The two picks exported in one process with --drop-idle: (summary, dataset folder); two tests compare with it."""
    out = tmp_path_factory.mktemp("dropped") / "ds"
    return export_dataset(recorded, _opts(out, drop_idle=True), log=lambda line: None), out


def _rows(out) -> list[dict]:
    from lerobot.datasets import LeRobotDataset

    ds = LeRobotDataset("t/idle", root=out)
    return [ds[i] for i in range(len(ds))]


def test_idle_mask_keeps_motion_and_drops_stillness():
    still = {"action": np.zeros(3), "observation.state": np.zeros(3)}
    frames = [dict(still) for _ in range(5)]
    assert idle_mask(frames) == [True, False, False, False, False]  # the first frame is always kept
    # A slow motion (0.4 of the tolerance a frame) is kept every third frame, never dropped whole.
    slow = [{"action": np.full(3, k * 0.4 * IDLE_TOLERANCE), "observation.state": np.zeros(3)} for k in range(10)]
    assert idle_mask(slow) == [True, False, False, True, False, False, True, False, False, True]
    # Any one key moving keeps the frame: an object still settling is no pause.
    moving = [{**still, "observation.environment_state": np.array([0.0, 0.0, k * 0.01])} for k in range(4)]
    assert idle_mask(moving) == [True] * 4


@pytest.mark.e2e  # LeRobot exports, rendered
def test_drop_idle_leaves_out_the_pause_and_keeps_frames_whole(recorded, dropped, tmp_path):
    plain = export_dataset(recorded, _opts(tmp_path / "plain"), log=lambda line: None)
    dropped, dropped_out = dropped
    assert plain.idle_dropped == 0 and dropped.episodes == plain.episodes == 2
    assert dropped.frames + dropped.idle_dropped == plain.frames
    # The pause is 18 ticks at 15 Hz, the first few of them the arm settling (kept): most of it goes.
    assert dropped.idle_dropped >= 2 * 12, dropped.idle_dropped
    a, b = _rows(tmp_path / "plain"), _rows(dropped_out)
    assert len(b) == dropped.frames
    # Every kept frame is a recorded frame, images included (the worker's camera too), in order.
    position = 0
    for row in b:
        while not all(np.array_equal(a[position][k].numpy(), row[k].numpy()) for k in KEYS):
            position += 1
        for camera in CAMERAS:
            assert np.array_equal(a[position][camera].numpy(), row[camera].numpy()), (position, camera)
        position += 1
    # No two frames kept in a row stand still; frame indices run without gaps.
    for before, after in zip(b, b[1:]):
        if int(after["episode_index"]) == int(before["episode_index"]):
            assert int(after["frame_index"]) == int(before["frame_index"]) + 1
            assert max(float((after[k] - before[k]).abs().max()) for k in KEYS) > IDLE_TOLERANCE


def test_drop_idle_in_parallel_and_on_the_command_line(recorded, dropped, tmp_path):
    serial, serial_out = dropped
    parallel = export_dataset(recorded, _opts(tmp_path / "two", drop_idle=True, workers=2), log=lambda line: None)
    assert (parallel.frames, parallel.idle_dropped) == (serial.frames, serial.idle_dropped)
    a, b = _rows(serial_out), _rows(tmp_path / "two")
    assert all(np.array_equal(x["action"].numpy(), y["action"].numpy()) for x, y in zip(a, b)) and len(a) == len(b)
    result = run_cli("export", str(recorded[0]), "--out", str(tmp_path / "cli"), "--repo-id", "t/idle", "--cameras", "none",
                     "--drop-idle")
    assert result.returncode == 0, result.stderr[-2000:]
    assert "idle frames left out" in result.stdout
    assert "Cannot enable progress bars" not in result.stderr


@pytest.mark.e2e  # LeRobot exports, rendered, cut and resumed
def test_a_resume_must_ask_for_the_same_drop_idle(recorded, tmp_path):
    out = tmp_path / "cut"

    def stop_after_the_first(episodes: int, frames: int) -> None:
        raise KeyboardInterrupt

    cut = export_dataset(recorded, _opts(out, piece_episodes=1, on_episode=stop_after_the_first), log=lambda line: None)
    assert cut.interrupted and cut.episodes == 1
    with pytest.raises(ResumeError, match="drop_idle"):
        export_dataset(recorded, _opts(out, piece_episodes=1, resume=True, drop_idle=True), log=lambda line: None)
    done = export_dataset(recorded, _opts(out, piece_episodes=1, resume=True), log=lambda line: None)
    assert done.dataset_episodes == 2


def test_help_names_the_flag():
    result = run_main("export", "--help")  # in this process
    assert result.returncode == 0 and "--drop-idle" in result.stdout
    assert (ROOT / "docs" / "export.md").read_text().count("--drop-idle") >= 1
