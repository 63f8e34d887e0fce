"""The export's image statistics: LeRobot's RunningQuantileStats, computed from value counts.

Fed the same rendered frames of a real recording, the counted class must give
LeRobot's own histograms, bin edges, min, max and quantiles exactly, and its
mean and std to float32 rounding (LeRobot sums in float32, the counts in float64).
"""

from __future__ import annotations

import numpy as np
import pytest

from replay import load_episode, replay_states
from replay.export.stats import image_stats
from replay.render import FastRenderer
from tests.support import PICK, run_json



@pytest.fixture(scope="module")
def frames(tmp_path_factory):
    """Front and wrist frames, 96x72, of a scripted pick (the wrist view changes most)."""
    rec = tmp_path_factory.mktemp("stats")
    summary = run_json("run", "--device", f"script:{PICK}", "--record", str(rec), "--control-hz", "10", "--json")
    ep = load_episode(summary["files"][0])
    model = ep.build_model()
    out: dict[str, list[np.ndarray]] = {"front": [], "wrist": []}
    with FastRenderer(model, 96, 72, list(out)) as renderer:
        for _, data in replay_states(ep, model):
            for name in out:
                out[name].append(renderer.render(data, name))
    return out


@pytest.fixture(scope="module")
def compute_stats():
    """LeRobot's statistics module, imported when a test runs: at collection it cost every worker seconds (torch)."""
    import lerobot.datasets.compute_stats as module

    return module


def _feed(stats, images) -> dict:
    for image in images:  # as LeRobot's encoder thread feeds them: (H*W, 3) uint8
        stats.update(image.reshape(-1, 3))
    return stats


@pytest.mark.parametrize("camera", ["front", "wrist"])
def test_counted_stats_equal_lerobots(frames, camera, compute_stats):
    images = frames[camera]
    assert len(images) > 20 and images[0].dtype == np.uint8
    theirs = _feed(compute_stats.RunningQuantileStats(), images)
    with image_stats():
        counted = compute_stats.RunningQuantileStats  # what LeRobot's encoder threads import while exporting
        assert counted is not theirs.__class__ and issubclass(counted, theirs.__class__)
        ours = _feed(counted(), images)
    assert compute_stats.RunningQuantileStats is theirs.__class__  # put back afterwards

    for a, b in zip(theirs._histograms, ours._histograms, strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(theirs._bin_edges, ours._bin_edges, strict=True):
        np.testing.assert_array_equal(a, b)
    s, o = theirs.get_statistics(), ours.get_statistics()
    assert set(s) == set(o)
    for key in ("min", "max", "count", "q01", "q10", "q50", "q90", "q99"):
        np.testing.assert_array_equal(s[key], o[key], err_msg=key)
        assert s[key].dtype == o[key].dtype, key
    np.testing.assert_allclose(s["mean"], o["mean"], rtol=1e-6)
    np.testing.assert_allclose(s["std"], o["std"], atol=0.05)  # of 255: float32 mean-of-squares rounding
    # The figures describe the frames themselves.
    pixels = np.concatenate([i.reshape(-1, 3) for i in images]).astype(np.float64)
    np.testing.assert_allclose(o["mean"], pixels.mean(axis=0), rtol=1e-5)
    np.testing.assert_allclose(o["std"], pixels.std(axis=0), atol=0.01)


def test_other_dtypes_go_to_lerobots_code(frames, compute_stats):
    floats = [f.reshape(-1, 3).astype(np.float32) / 255 for f in frames["front"][:5]]
    theirs = compute_stats.RunningQuantileStats()
    with image_stats():
        ours = compute_stats.RunningQuantileStats()
    for batch in floats:
        theirs.update(batch)
        ours.update(batch)
    for key, value in theirs.get_statistics().items():
        np.testing.assert_array_equal(value, ours.get_statistics()[key], err_msg=key)
