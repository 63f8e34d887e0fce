"""The export's offscreen renderer: real MuJoCo rendering of a real recording (no LeRobot needed)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from replay import load_episode, replay_states
from replay.features import feature_key
from replay.render import DEFAULTS, TUNED, FastRenderer, RenderError, tune_model
from tests.support import PICK, run_json



@pytest.fixture(scope="module")
def episode(tmp_path_factory):
    rec = tmp_path_factory.mktemp("render")
    summary = run_json("run", "--device", f"script:{PICK}", "--record", str(rec), "--control-hz", "10", "--json")
    return load_episode(summary["files"][0])


def test_tuning_works_on_a_copy(episode):
    model = episode.build_model()
    before = (model.vis.quality.shadowsize, model.vis.quality.offsamples, model.vis.global_.offwidth,
              model.light_castshadow.copy(), model.geom_size.copy(), model.mat_reflectance.copy())
    tuned = tune_model(model, 96, 64)
    assert (tuned.vis.quality.shadowsize, tuned.vis.quality.offsamples) == (0, 0)
    assert (tuned.vis.global_.offwidth, tuned.vis.global_.offheight) == (96, 64)
    assert not tuned.light_castshadow.any() and not tuned.mat_reflectance.any()
    assert (tuned.vis.quality.numslices, tuned.vis.quality.numstacks) == (12, 7)  # few facets for a small image
    big = tune_model(model, 640, 480).vis.quality
    assert (big.numslices, big.numstacks, big.numquads) == (28, 16, model.vis.quality.numquads)
    floor = model.geom("floor").id
    assert model.geom_size[floor, 0] == 0 and tuned.geom_size[floor, 0] > 5  # infinite floor made finite
    after = (model.vis.quality.shadowsize, model.vis.quality.offsamples, model.vis.global_.offwidth,
             model.light_castshadow, model.geom_size, model.mat_reflectance)
    assert before[:3] == after[:3]
    for a, b in zip(before[3:], after[3:]):
        assert np.array_equal(a, b)


def test_tuned_images_frame_the_scene_and_match_mujocos_look(episode):
    model = episode.build_model()
    cams = ["front", "overhead", "wrist"]
    with FastRenderer(model, 96, 72, cams) as fast, FastRenderer(model, 96, 72, cams, settings=DEFAULTS) as slow:
        frames = {}
        for k, data in replay_states(episode, model):
            if k in (0, episode.steps - 1):
                frames[k] = (fast.render_all(data), slow.render_all(data))
        for k, (tuned, default) in frames.items():
            for name, a, b in zip(cams, tuned, default):
                assert a.shape == (72, 96, 3) and a.dtype == np.uint8
                assert a.std() > 10, f"{name} at step {k} is blank"
                # Same scene, same framing: only shadows, anti-aliasing and floor shading differ.
                diff = np.abs(a.astype(int) - b.astype(int)).mean()
                assert diff < 25, f"{name} at step {k} differs from MuJoCo's default look by {diff:.1f}"
        for i, name in enumerate(cams):
            moved = np.abs(frames[0][0][i].astype(int) - frames[episode.steps - 1][0][i].astype(int)).mean()
            assert moved > 1, f"{name} shows no motion over the episode"


def test_fitted_tessellation_changes_only_edge_pixels(episode):
    """At 224x224 the coarser round primitives are not visible: a few edge pixels move."""
    model = episode.build_model()
    cams = ["front", "overhead", "wrist"]
    full = replace(TUNED, fit_tessellation=False)
    with FastRenderer(model, 224, 224, cams) as fitted, FastRenderer(model, 224, 224, cams, settings=full) as fine:
        for k, data in replay_states(episode, model):
            if k % 20:
                continue
            for name, a, b in zip(cams, fitted.render_all(data), fine.render_all(data)):
                diff = np.abs(a.astype(int) - b.astype(int))
                assert diff.mean() < 1.5 and (diff.max(axis=2) > 30).mean() < 0.01, f"{name} at step {k}"


def test_unknown_camera_names_the_cameras(episode):
    with pytest.raises(RenderError, match=r"no camera 'side' .*cameras: front, overhead, room, wrist"):
        FastRenderer(episode.build_model(), 32, 32, ["front", "side"])


def test_camera_feature_keys_are_valid_names():
    assert feature_key("front") == "observation.images.front"
    assert feature_key("left/wrist") == "observation.images.left_wrist"
    assert feature_key("right/wrist cam") == "observation.images.right_wrist_cam"


def test_the_export_stream_renders_cameras_in_two_threads_as_one_renderer_does(episode):
    """The stream splits the cameras between its thread and a render worker (a GL context each): the frames
    are the ones a single renderer draws, in order, for every camera."""
    from replay.export.stream import EpisodeEnd, FrameStream

    model = episode.build_model()
    cameras = ["front", "overhead", "wrist"]
    keys = [feature_key(c) for c in cameras]
    stream = FrameStream(model, (48, 40), cameras)
    try:
        stream.start([lambda: episode, lambda: episode], "joint", lambda ep: "lift", keys, [False, True, False])
        items = list(stream)
    finally:
        stream.close()
    frames = [f for f in items if not isinstance(f, EpisodeEnd)]
    assert [e.steps for e in items if isinstance(e, EpisodeEnd)] == [episode.steps] * 2
    assert len(frames) == 2 * episode.steps
    with FastRenderer(model, 48, 40, cameras) as renderer:
        for k, data in replay_states(episode, model):
            for c, key in enumerate(keys):
                expected = renderer.render(data, c, channel_first=(c == 1))
                for frame in (frames[k], frames[episode.steps + k]):
                    np.testing.assert_array_equal(frame[key], expected, err_msg=f"step {k} {key}")


def test_a_pooled_renderer_is_lent_again_in_another_thread_and_draws_what_a_fresh_one_does(episode):
    """replay.render_pool: a renderer given back is lent to the next use of its size, in another thread, with
    another camera (one GL context made, not two), and its images equal a fresh renderer's, pixel for pixel."""
    import threading

    from replay.render_pool import RendererPool

    model = episode.build_model()
    import copy

    picks = [copy.copy(data) for k, data in replay_states(episode, model) if k in (0, episode.steps // 2)]
    assert len(picks) == 2
    pool = RendererPool(keep=2)
    got: dict[str, list[np.ndarray]] = {}

    def use(camera: str) -> None:
        with pool.renderer(model, 48, 40, [camera]) as renderer:
            got[camera] = [renderer.render(data, 0) for data in picks]

    for camera in ("front", "wrist"):
        worker = threading.Thread(target=use, args=(camera,))
        worker.start()
        worker.join()
    assert (pool.created, pool.lent) == (1, 2)
    with pool.renderer(model, 32, 24, ["front"]):  # another size: a renderer of its own
        pass
    assert (pool.created, pool.lent) == (2, 3)
    with FastRenderer(model, 48, 40, ["front", "wrist"]) as fresh:
        for c, camera in enumerate(("front", "wrist")):
            for data, image in zip(picks, got[camera]):
                np.testing.assert_array_equal(image, fresh.render(data, c), err_msg=camera)
    with pytest.raises(RenderError, match="no camera 'nope'"):
        with pool.renderer(model, 48, 40, ["nope"]):
            pass
    assert pool.created == 2  # the failed reload closed the lent renderer; nothing broken stays in the pool
    pool.clear()
