"""`teleop export --workers K` / `--ray`: shards exported in parallel and merged by LeRobot's aggregation
hold what a single-process export holds (frames, values, features, episode boundaries, tasks).

Three short recorded episodes (two lengths, 15 Hz), one camera at 32x32, so that each export
takes seconds. With 2 workers they make 2 shards; on Ray, 3 shards on 2 CPUs, so a worker
runs more than one shard and the merge joins more than two.
"""

from __future__ import annotations

import os
import time

import numpy as np
import pytest

from tests.support import assert_one_line_error, column, open_dataset, record_script, run_cli, run_main, write_script

import lerobot  # noqa: E402,F401  (the test command installs the lerobot extra)
os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever

from replay.export import ExportError, ExportOptions  # noqa: E402
from replay.export import export_dataset  # noqa: E402
from replay.export.shards import shard_count, split  # noqa: E402

HZ = "15"
KEY = "observation.images.front"
VALUES = ("action", "observation.state", "observation.ee_pose", "episode_index", "frame_index", "index",
          "task_index", "timestamp")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    root = tmp_path_factory.mktemp("episodes")
    rec = root / "moves"
    longer = write_script(root / "a.json", [{"duration": 0.8, "move": [0, 0.05, 0.02]}])
    shorter = write_script(root / "b.json", [{"duration": 0.5, "move": [0.03, 0, 0]}])
    record_script(rec, longer, "--control-hz", HZ, "--episodes", "2")
    record_script(rec, shorter, "--control-hz", HZ, "--seed", "3")
    files = sorted(rec.glob("*.mcap"))
    assert len(files) == 3
    return {"dir": rec, "files": files}


def _opts(out, **kw) -> ExportOptions:
    return ExportOptions(out=out, repo_id="t/par", cameras=["front"], image_size=(32, 32), progress=False, **kw)


@pytest.fixture(scope="module")
def single(recorded, tmp_path_factory):
    """The reference: one process, with video and with PNG images."""
    root = tmp_path_factory.mktemp("single")
    video = export_dataset([recorded["dir"]], _opts(root / "video"))
    png = export_dataset([recorded["dir"]], _opts(root / "png", video=False))
    return {"video": video, "png": png}


def _assert_same_dataset(ref_out, out, exact_images: bool) -> None:
    ref, ds = open_dataset(ref_out, "t/par"), open_dataset(out, "t/par")
    assert (ds.num_episodes, ds.num_frames, ds.fps) == (ref.num_episodes, ref.num_frames, ref.fps) == (3, ref.num_frames, 15)
    assert ds.meta.robot_type == ref.meta.robot_type
    assert set(ds.meta.features) == set(ref.meta.features)
    for key, ft in ref.meta.features.items():
        other = ds.meta.features[key]
        assert (other["dtype"], tuple(other["shape"]), other.get("names")) == (ft["dtype"], tuple(ft["shape"]), ft.get("names")), key
        if ft["dtype"] == "video":
            theirs, ours = ft["info"], other["info"]
            for field in ("video.codec", "video.height", "video.width", "video.pix_fmt", "video.fps"):
                assert theirs[field] == ours[field], field
    for key in VALUES:  # every frame's values, indices and timestamps
        np.testing.assert_array_equal(column(ds, key), column(ref, key), err_msg=key)
    assert list(ds.meta.tasks.index) == list(ref.meta.tasks.index)
    for i in range(3):
        a, b = ref.meta.episodes[i], ds.meta.episodes[i]
        for field in ("episode_index", "dataset_from_index", "dataset_to_index", "length", "tasks"):
            assert list(np.atleast_1d(a[field])) == list(np.atleast_1d(b[field])), (i, field)
    # statistics merged from the shards' own; the indices the merge renumbers, from their merged values
    for key in ("action", "observation.state", "index", "episode_index", "task_index"):
        for stat in ("mean", "std", "min", "max"):
            np.testing.assert_allclose(ds.meta.stats[key][stat], ref.meta.stats[key][stat], rtol=1e-5, atol=1e-6)
    diffs = []
    for i in range(ref.num_frames):  # every image, decoded through the episode's video offsets
        a, b = ref[i][KEY].numpy(), ds[i][KEY].numpy()
        if exact_images:
            np.testing.assert_array_equal(a, b, err_msg=f"frame {i}")
        diffs.append(np.abs(a - b).mean())
    assert max(diffs) < 0.01, max(diffs)  # floats in [0, 1]: well under 3 of 255 steps


def test_split_keeps_order_and_balances_frames():
    assert split([10, 10, 10, 10], 2) == [range(0, 2), range(2, 4)]
    assert split([30, 5, 5, 5, 5, 10], 3) == [range(0, 1), range(1, 4), range(4, 6)]  # 30, 15, 15
    assert split([5, 5], 8) == [range(0, 1), range(1, 2)]  # never an empty shard
    assert split([7], 1) == [range(0, 1)]
    runs = split(list(range(1, 20)), 6)
    assert [i for r in runs for i in r] == list(range(19)) and len(runs) == 6
    assert [shard_count(n, 2) for n in (1, 3, 7, 8, 100)] == [1, 2, 2, 4, 4]


def test_workers_export_matches_a_single_process_export(recorded, single, tmp_path):
    """`teleop export --workers 2` (the CLI, in a fresh process): the same dataset, one summary line."""
    out = tmp_path / "par"
    result = run_cli("export", str(recorded["dir"]), "--out", str(out), "--repo-id", "t/par", "--cameras", "front",
                     "--image-size", "32x32", "--workers", "2")
    assert result.returncode == 0, result.stderr[-3000:]
    ref = single["video"]
    assert result.stdout.startswith(f"exported 3 episodes, {ref.frames} frames") and result.stdout.count("\n") == 1
    assert "3 episodes in all)" in result.stdout
    lines = [line for line in result.stderr.splitlines() if line.strip()]  # no merge bars, no worker noise
    assert len(lines) <= 1 and all(line.startswith("video: pyav decoder") for line in lines), result.stderr[-2000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["par"]  # the shards are gone
    _assert_same_dataset(ref.out, out, exact_images=False)


def test_ray_export_matches_a_single_process_export(recorded, single, tmp_path):
    """On a local Ray instance (ray.init in the driver), 3 shards on its 2 CPUs; PNG images, so every
    pixel must match."""
    import ray  # the test command installs the cluster extra: no skip

    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level="ERROR")
    try:
        out = tmp_path / "ray"
        summary = export_dataset([recorded["dir"]], _opts(out, video=False, ray="auto", workers=3))
    finally:
        ray.shutdown()
    ref = single["png"]
    assert (summary.episodes, summary.frames, summary.dataset_episodes, summary.fps) == (3, ref.frames, 3, 15)
    assert summary.bytes > 0 and summary.out == out and not summary.interrupted
    assert sorted(p.name for p in tmp_path.iterdir()) == ["ray"]
    _assert_same_dataset(ref.out, out, exact_images=True)


def test_bad_parallel_flags_are_one_line(recorded, tmp_path):
    out = str(tmp_path / "x")
    common = ("export", str(recorded["dir"]), "--out", out, "--repo-id", "t/x")
    assert_one_line_error(run_main(*common, "--workers", "0"), "--workers '0'", "1 or more")  # in this process
    assert_one_line_error(run_main(*common, "--workers", "two"), "--workers 'two'")
    t0 = time.monotonic()
    result = run_cli(*common, "--ray", "127.0.0.1:9")  # nothing listens on the discard port
    assert_one_line_error(result, "cannot reach a Ray cluster at 127.0.0.1:9")
    assert time.monotonic() - t0 < 60  # ray.init alone would retry for minutes
    with pytest.raises(ExportError, match="appending runs in one process"):
        export_dataset([recorded["dir"]], _opts(tmp_path / "x", workers=2, append=True))
    assert not (tmp_path / "x").exists()
