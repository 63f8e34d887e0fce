"""`teleop export`: real recordings (the real `teleop run --record`), real LeRobot, real MuJoCo rendering.

Episodes are recorded once per module at 15 Hz (short, so exports stay quick):
two scripted picks that succeed and one short move that does not. Images are
64x64 to keep video encoding and decoding cheap.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import subprocess
import sys

import mujoco
import numpy as np
import pytest

from tests.support import (PICK, ROOT, assert_one_line_error, column, open_dataset, record_script, run_cli, run_main,
                           run_script, write_script)

import lerobot  # noqa: E402,F401  (the test command installs the lerobot extra)
os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever

from replay import load_episode  # noqa: E402
from replay.export import ExportError, ExportOptions  # noqa: E402
from replay.export import export_dataset  # noqa: E402

HZ = "15"
SIZE = "64x64"


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """episode_000000/1: successful picks (seeds 0, 1); episode_000002: fails its task."""
    root = tmp_path_factory.mktemp("episodes")
    rec = root / "lift"
    picks = record_script(rec, PICK, "--control-hz", HZ, "--episodes", "2")
    assert [e["success"] for e in picks["per_episode"]] == [True, True]
    fail_script = write_script(root / "fail.json", [{"duration": 0.6, "move": [0, 0.05, 0]}])
    fail = record_script(rec, fail_script, "--control-hz", HZ, "--seed", "7")
    assert fail["success"] is False
    files = sorted(rec.glob("*.mcap"))
    assert len(files) == 3
    return {"dir": rec, "files": files, "root": root, "fail_script": fail_script}


@pytest.fixture(scope="module")
def exported(recorded, tmp_path_factory):
    """The whole directory exported with the CLI's defaults (front + wrist, joint actions)."""
    out = tmp_path_factory.mktemp("datasets") / "lift"
    result = run_cli("export", str(recorded["dir"]), "--out", str(out), "--repo-id", "test/lift", "--image-size", SIZE)
    assert result.returncode == 0, result.stderr[-3000:]
    return {"out": out, "stdout": result.stdout, "stderr": result.stderr}


def _episodes(recorded):
    return [load_episode(f) for f in recorded["files"]]


def _same_rotation(a: np.ndarray, b: np.ndarray, atol: float = 2e-6) -> bool:
    """Quaternion rows equal up to sign (q and -q are one rotation)."""
    dots = np.abs(np.sum(a * b, axis=-1))
    return bool(np.all(dots > 1 - atol))


def test_export_loads_offline_with_recorded_values(recorded, exported):
    eps = _episodes(recorded)
    ds = open_dataset(exported["out"], "test/lift")
    steps = [e.steps for e in eps]
    assert ds.num_episodes == 3 and ds.num_frames == sum(steps) == len(ds)
    assert ds.fps == 15 and ds.meta.robot_type == "panda"
    assert "exported 3 episodes" in exported["stdout"] and f"{sum(steps)} frames" in exported["stdout"]

    feats = ds.meta.features
    joints = list(eps[0].meta.arms[0].joints)
    assert feats["observation.state"]["names"] == [*joints, "gripper"]
    assert feats["action"]["names"] == [*joints, "gripper"]
    assert feats["observation.ee_pose"]["names"] == ["x", "y", "z", "qw", "qx", "qy", "qz"]
    assert feats["observation.images.front"]["dtype"] == "video"
    # Declared channel-last, as LeRobot's recorder declares cameras.
    assert tuple(feats["observation.images.wrist"]["shape"]) == (64, 64, 3)
    assert feats["observation.images.wrist"]["names"] == ["height", "width", "channels"]

    # Episode boundaries, frame order and task text.
    meta_eps = ds.meta.episodes
    episode_index, frame_index = column(ds, "episode_index"), column(ds, "frame_index")
    task_index = column(ds, "task_index")
    start = 0
    for i, ep in enumerate(eps):
        row = meta_eps[i]
        assert (row["dataset_from_index"], row["dataset_to_index"], row["length"]) == (start, start + ep.steps, ep.steps)
        assert row["tasks"] == [ep.meta.task]
        assert np.all(episode_index[start:start + ep.steps] == i)
        assert np.array_equal(frame_index[start:start + ep.steps], np.arange(ep.steps))
        start += ep.steps
    assert set(ds.meta.tasks.index) == {"Pick up the red cube and lift it."}
    assert np.all(task_index == 0)
    assert ds[0]["task"] == "Pick up the red cube and lift it."

    # Values: actions are the recorded ctrl, states the recorded qpos, EE poses the replayed site pose.
    action, state, pose = column(ds, "action"), column(ds, "observation.state"), column(ds, "observation.ee_pose")
    start = 0
    for ep in eps:
        rows = slice(start, start + ep.steps)
        arm = ep.meta.arms[0]
        model = ep.build_model()
        act_ids = [model.actuator(a).id for a in arm.actuators]
        qadr = [model.joint(j).qposadr[0] for j in arm.joints]
        grip = model.actuator(arm.gripper_actuator).id
        assert np.array_equal(action[rows, :7], ep.ctrl[:, act_ids].astype(np.float32))
        assert np.array_equal(action[rows, 7], ep.gripper[:, 0].astype(np.float32))  # 1 open .. 0 closed
        span = arm.gripper_open - arm.gripper_closed
        assert np.array_equal(action[rows, 7], ((ep.ctrl[:, grip] - arm.gripper_closed) / span).astype(np.float32))
        assert np.array_equal(state[rows, :7], ep.qpos[:, qadr].astype(np.float32))
        assert np.all((state[rows, 7] > -0.05) & (state[rows, 7] < 1.05))
        # The recorded ee_pose is after step k, i.e. at state k+1.
        np.testing.assert_allclose(pose[rows][1:, :3], ep.ee_pose[:-1, 0, :3], atol=1e-6)
        assert _same_rotation(pose[rows][1:, 3:], ep.ee_pose[:-1, 0, 3:])
        start += ep.steps


def _torchcodec_loads() -> bool:
    try:
        import torchcodec  # noqa: F401
    except (ImportError, OSError, RuntimeError):  # RuntimeError: FFmpeg's shared libraries are missing
        return False
    return True


def test_export_prints_its_summary_and_at_most_the_video_decoder(recorded, exported):
    """A successful export: one summary line on stdout; on stderr at most the one line naming
    LeRobot's video decoder (never torchcodec's ~100 lines of loading tracebacks)."""
    assert exported["stdout"].startswith("exported 3 episodes") and exported["stdout"].count("\n") == 1
    for noise in ("Traceback", "Could not load", "WARNING", "libtorchcodec"):
        assert noise not in exported["stderr"], exported["stderr"][:2000]
    lines = [line for line in exported["stderr"].splitlines() if line.strip()]
    if _torchcodec_loads():
        assert lines == []
    else:  # this machine lacks FFmpeg's shared libraries (or torchcodec): one line says so
        assert len(lines) == 1 and lines[0].startswith("video: pyav decoder (torchcodec unavailable"), lines

    # An export refused after LeRobot has loaded is still the one error line (no decoder line first).
    refused = run_cli("export", str(recorded["files"][0]), "--out", str(exported["out"]), "--repo-id", "test/lift",
                      "--image-size", SIZE, "--no-video", "--append")
    assert_one_line_error(refused, "does not match")


def test_images_are_rendered_and_change(recorded, exported):
    ds = open_dataset(exported["out"], "test/lift")
    steps = load_episode(recorded["files"][0]).steps
    for key in ("observation.images.front", "observation.images.wrist"):
        first, last = ds[0][key].numpy(), ds[steps - 1][key].numpy()
        assert first.shape == (3, 64, 64)
        for img in (first, last):
            assert img.std() > 0.05, f"{key} is blank"  # floats in [0, 1]
        assert np.abs(first - last).mean() > 0.02, f"{key} did not change over the episode"


def test_only_success_and_append(recorded, tmp_path):
    out = tmp_path / "ds"
    eps = _episodes(recorded)
    s1 = export_dataset([recorded["dir"]], ExportOptions(out=out, repo_id="test/append", cameras=["front"],
                                                           image_size=(32, 32), only_success=True, progress=False))
    assert (s1.episodes, s1.skipped_failed, s1.frames) == (2, 1, eps[0].steps + eps[1].steps)
    ds = open_dataset(out, "test/append")
    assert ds.num_episodes == 2

    # Append the failed one under another task text; a plain export into `out` is refused.
    with pytest.raises(ExportError, match="already exists"):
        export_dataset([recorded["files"][2]], ExportOptions(out=out, repo_id="test/append", cameras=["front"],
                                                              image_size=(32, 32), progress=False))
    s2 = export_dataset([recorded["files"][2]], ExportOptions(out=out, repo_id="test/append", cameras=["front"],
                                                               image_size=(32, 32), append=True, task="Wave.", progress=False))
    assert (s2.episodes, s2.dataset_episodes) == (1, 3)
    ds = open_dataset(out, "test/append")
    assert ds.num_episodes == 3 and ds.num_frames == sum(e.steps for e in eps)
    last = ds.meta.episodes[2]
    assert last["tasks"] == ["Wave."] and last["dataset_from_index"] == eps[0].steps + eps[1].steps
    assert ds[ds.num_frames - 1]["task"] == "Wave."
    action = column(ds, "action")
    assert np.array_equal(action[-eps[2].steps:, :7], eps[2].ctrl[:, :7].astype(np.float32))
    assert ds[ds.num_frames - 1]["observation.images.front"].std() > 0.05

    # Appending episodes that do not fit the dataset's features is refused, naming the difference.
    with pytest.raises(ExportError, match="does not match"):
        export_dataset([recorded["files"][2]], ExportOptions(out=out, repo_id="test/append", cameras=["front"],
                                                              image_size=(48, 32), append=True, progress=False))
    assert open_dataset(out, "test/append").num_episodes == 3


def test_append_to_a_channel_first_dataset_keeps_its_layout(recorded, tmp_path):
    """Exports of November 2026 declared video cameras (3, H, W): appending keeps that layout."""
    out = tmp_path / "chw"
    opts = dict(out=out, repo_id="test/chw", cameras=["front"], image_size=(32, 24), progress=False)
    export_dataset(recorded["files"][:1], ExportOptions(**opts))
    info_path = out / "meta" / "info.json"
    info = json.loads(info_path.read_text())
    feature = info["features"]["observation.images.front"]
    assert feature["shape"] == [24, 32, 3]
    feature["shape"], feature["names"] = [3, 24, 32], ["channels", "height", "width"]  # as those exports wrote it
    info_path.write_text(json.dumps(info, indent=4))

    export_dataset(recorded["files"][1:2], ExportOptions(**opts, append=True))
    ds = open_dataset(out, "test/chw")
    assert ds.num_episodes == 2
    assert list(ds.meta.features["observation.images.front"]["shape"]) == [3, 24, 32]
    last = ds[ds.num_frames - 1]["observation.images.front"]
    assert tuple(last.shape) == (3, 24, 32) and last.std() > 0.05


def test_image_stats_are_per_channel_and_match_the_frames(exported):
    """LeRobot's per-frame image statistics (what normalization uses), counted per channel (replay/export/stats.py)."""
    ds = open_dataset(exported["out"], "test/lift")
    for key in ("observation.images.front", "observation.images.wrist"):
        stats = ds.meta.stats[key]
        assert {"mean", "std", "min", "max", "q01", "q99"} <= set(stats)
        assert np.asarray(stats["mean"]).shape == (3, 1, 1)
        frames = np.stack([ds[i][key].numpy() for i in range(0, ds.num_frames, 5)])  # (N, 3, H, W) in [0, 1]
        # Per channel, as decoded from the (lossy) video: within a few 8-bit steps of the stats.
        np.testing.assert_allclose(np.asarray(stats["mean"]).ravel(), frames.mean(axis=(0, 2, 3)), atol=0.02)
        np.testing.assert_allclose(np.asarray(stats["std"]).ravel(), frames.std(axis=(0, 2, 3)), atol=0.02)
        lo, hi = np.asarray(stats["min"]), np.asarray(stats["max"])
        assert np.all(lo < hi) and np.all(lo - 1e-6 <= np.asarray(stats["q01"]))  # LeRobot pads edges by 1e-10
        assert np.all(np.asarray(stats["q99"]) <= hi + 1e-6)


def _codec(out, repo_id: str, key: str = "observation.images.front") -> str:
    return open_dataset(out, repo_id).meta.features[key]["info"]["video.codec"]


def test_video_codecs_and_append_keeps_the_datasets_codec(recorded, exported, tmp_path):
    assert _codec(exported["out"], "test/lift") == "h264"  # the default
    out = tmp_path / "av1"
    opts = dict(out=out, repo_id="test/av1", cameras=["front"], image_size=(32, 32), progress=False)
    export_dataset(recorded["files"][:1], ExportOptions(**opts, vcodec="av1"))
    assert _codec(out, "test/av1") == "av1"

    # Appended episodes go into the same video files, so they take the dataset's codec.
    with pytest.raises(ExportError, match="holds av1 video"):
        export_dataset(recorded["files"][1:2], ExportOptions(**opts, vcodec="h264", append=True))
    export_dataset(recorded["files"][1:2], ExportOptions(**opts, append=True))
    ds = open_dataset(out, "test/av1")
    assert ds.num_episodes == 2 and _codec(out, "test/av1") == "av1"
    first, last = ds[0]["observation.images.front"].numpy(), ds[ds.num_frames - 1]["observation.images.front"].numpy()
    assert first.std() > 0.05 and last.std() > 0.05 and np.abs(first - last).mean() > 0.02

    with pytest.raises(ExportError, match="video codec 'vp9'"):
        export_dataset(recorded["files"][:1], ExportOptions(**{**opts, "out": tmp_path / "vp9"}, vcodec="vp9"))
    result = run_main("export", str(recorded["files"][0]), "--out", str(tmp_path / "png"), "--repo-id", "test/png",
                      "--no-video", "--vcodec", "h264")
    assert_one_line_error(result, "video codec", "without video")
    assert not (tmp_path / "png").exists()


def test_ee_actions_and_images_without_video(recorded, tmp_path):
    ep = load_episode(recorded["files"][0])
    files = [recorded["files"][0]]
    ee_pose = export_dataset(files, ExportOptions(out=tmp_path / "pose", repo_id="t/pose", cameras=[],
                                                  action="ee_pose", progress=False))
    assert ee_pose.frames == ep.steps
    ds = open_dataset(tmp_path / "pose", "t/pose")
    assert ds.meta.features["action"]["names"] == ["x", "y", "z", "qw", "qx", "qy", "qz", "gripper"]
    assert not any(k.startswith("observation.images") for k in ds.meta.features)
    act = column(ds, "action")
    np.testing.assert_array_equal(act[:, :3], ep.ee_target[:, 0, :3].astype(np.float32))
    assert _same_rotation(act[:, 3:7], ep.ee_target[:, 0, 3:])
    np.testing.assert_array_equal(act[:, 7], ep.gripper[:, 0].astype(np.float32))

    export_dataset(files, ExportOptions(out=tmp_path / "delta", repo_id="t/delta", cameras=["wrist"], image_size=(32, 24),
                                        action="ee_delta", video=False, progress=False))
    ds = open_dataset(tmp_path / "delta", "t/delta")
    assert ds.meta.features["observation.images.wrist"]["dtype"] == "image"
    act, pose = column(ds, "action"), column(ds, "observation.ee_pose")
    # current pose + delta = commanded target
    np.testing.assert_allclose(pose[:, :3] + act[:, :3], ep.ee_target[:, 0, :3], atol=2e-6)
    for k in range(0, ep.steps, 7):
        turned = np.empty(4)
        mujoco.mju_axisAngle2Quat(turned, act[k, 3:6] / max(np.linalg.norm(act[k, 3:6]), 1e-12), np.linalg.norm(act[k, 3:6]))
        target = np.empty(4)
        mujoco.mju_mulQuat(target, turned, pose[k, 3:].astype(float))
        assert _same_rotation(target, ep.ee_target[k, 0, 3:], atol=1e-5)
    img = ds[5]["observation.images.wrist"]
    assert tuple(img.shape) == (3, 24, 32) and img.std() > 0.05


def test_bimanual_concatenates_arms_and_names_wrist_cameras(tmp_path):
    script = write_script(tmp_path / "bi.json", [{"duration": 0.4, "move": [0, 0, 0.03], "arm": 0},
                                                 {"duration": 0.4, "move": [0, 0, 0.03], "arm": 1}])
    rec = record_script(tmp_path / "bi", script, "--control-hz", HZ, "--robot", "bimanual", "--scene", "lift")
    out = tmp_path / "bi_ds"
    result = run_cli("export", str(tmp_path / "bi"), "--out", str(out), "--repo-id", "t/bi",
                     "--cameras", "front,wrist", "--image-size", "48x32")
    assert result.returncode == 0, result.stderr[-2000:]
    ds = open_dataset(out, "t/bi")
    ep = load_episode(rec["files"][0])
    feats = ds.meta.features
    assert {"observation.images.front", "observation.images.left_wrist", "observation.images.right_wrist"} <= set(feats)
    arms = ep.meta.arms
    assert feats["observation.state"]["names"] == [*arms[0].joints, "left/gripper", *arms[1].joints, "right/gripper"]
    assert tuple(feats["observation.ee_pose"]["shape"]) == (14,)
    model = ep.build_model()
    ids = [model.actuator(a).id for arm in arms for a in arm.actuators]
    action = column(ds, "action")
    n = len(arms[0].joints)
    np.testing.assert_array_equal(action[:, :n], ep.ctrl[:, ids[:n]].astype(np.float32))
    np.testing.assert_array_equal(action[:, n + 1:2 * n + 1], ep.ctrl[:, ids[n:]].astype(np.float32))
    for key in ("observation.images.left_wrist", "observation.images.right_wrist"):
        assert ds[0][key].std() > 0.05


# -- bad input: through the CLI's entry point in this process (run_main); the summary test above and the
# LeRobot-less one below keep a fresh process each -----------------------------------------------------------


def test_existing_out_without_append_is_refused(recorded, exported):
    result = run_main("export", str(recorded["dir"]), "--out", str(exported["out"]), "--repo-id", "test/lift")
    assert_one_line_error(result, str(exported["out"]), "already exists", "append")


def test_unknown_camera_lists_the_cameras(recorded, tmp_path):
    result = run_main("export", str(recorded["dir"]), "--out", str(tmp_path / "x"), "--repo-id", "t/x", "--cameras", "front,side")
    assert_one_line_error(result, "'side'", "front", "overhead", "wrist")
    assert not (tmp_path / "x").exists()


def test_mixed_scenes_and_rates_are_listed(recorded, tmp_path):
    other = tmp_path / "other"
    for flags in (["--control-hz", "10"], ["--scene", "stack", "--control-hz", HZ]):  # recorded in this process
        recorded_other = run_main("run", "--device", f"script:{recorded['fail_script']}", "--record", str(other), *flags)
        assert recorded_other.returncode == 0, recorded_other.stderr[-2000:]
    result = run_main("export", str(recorded["dir"]), str(other), "--out", str(tmp_path / "x"), "--repo-id", "t/x")
    assert_one_line_error(result, "different robots, scenes or rates", "scene lift / 15 Hz", "scene lift / 10 Hz",
                          "scene stack / 15 Hz", "episode_000000.mcap")


def test_bad_flags_and_files(recorded, tmp_path):
    assert_one_line_error(run_main("export", str(recorded["dir"]), "--out", str(tmp_path / "x"), "--repo-id", "t/x",
                                   "--image-size", "224"), "image size '224'", "WIDTHxHEIGHT")
    assert_one_line_error(run_main("export", str(tmp_path / "nothing"), "--out", str(tmp_path / "x"), "--repo-id", "t/x"),
                          "no such file")
    (tmp_path / "plain").mkdir()
    assert_one_line_error(run_main("export", str(recorded["dir"]), "--out", str(tmp_path / "plain"), "--repo-id", "t/x",
                                   "--append"), "not a LeRobot dataset")
    assert_one_line_error(run_main("export", str(recorded["root"] / "fail.json"), "--out", str(tmp_path / "x"),
                                   "--repo-id", "t/x"), "fail.json")
    assert not (tmp_path / "x").exists()


def test_without_lerobot_says_which_extra(recorded, tmp_path):
    code = ("import sys; sys.modules['lerobot'] = None; from teleop.cli.entry import main; "
            f"sys.exit(main(['export', {str(recorded['dir'])!r}, '--out', {str(tmp_path / 'x')!r}, '--repo-id', 't/x']))")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=ROOT, timeout=120)
    assert_one_line_error(result, "pip install 'mujoco-teleop[lerobot]'")


# -- a LeRobot policy trains on the export -----------------------------------------


def _readme_train_command() -> list[str]:
    """The `lerobot-train` command of docs/learning.md's "Train a policy" section, as argv."""
    text = (ROOT / "docs" / "learning.md").read_text()
    section = text[text.index("## Train a policy"):]
    block = section[section.index("```bash") + len("```bash"):]
    block = block[:block.index("```")].replace("\\\n", " ")
    lines = [line.split("#")[0].strip() for line in block.splitlines()]
    (command,) = [line for line in lines if line.startswith("lerobot-train ")]
    return shlex.split(command)


def test_act_policy_trains_on_exported_dataset_with_the_readme_command(exported, tmp_path):
    """The documented command verbatim, but 2 steps, in a fresh process, offline, on the CPU: a checkpoint
    that loads with the documented call and acts on a frame of the export."""
    import torch
    from lerobot.policies import make_pre_post_processors
    from lerobot.policies.act.modeling_act import ACTPolicy

    argv = _readme_train_command()
    assert "--policy.type=act" in argv and "--policy.device=cpu" in argv
    assert "--policy.pretrained_backbone_weights=null" in argv  # nothing to download
    assert "--dataset.root=datasets/lift" in argv and "--output_dir=outputs/act_lift" in argv
    argv = [re.sub(r"^--steps=\d+$", "--steps=2", a) for a in argv]
    assert "--steps=2" in argv
    exe = os.path.join(os.path.dirname(sys.executable), argv[0])
    assert os.path.exists(exe), "lerobot-train is missing: pip install -e '.[train]'"
    (tmp_path / "datasets").mkdir()
    (tmp_path / "datasets" / "lift").symlink_to(exported["out"], target_is_directory=True)
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "CUDA_VISIBLE_DEVICES": ""}
    result = run_script([exe, *argv[1:]], env, tmp_path, 900, ignore=("WANDB_MODE", "CUDA_VISIBLE_DEVICES"))
    assert result.returncode == 0, result.stderr[-3000:]

    model_dir = tmp_path / "outputs" / "act_lift" / "checkpoints" / "000002" / "pretrained_model"
    for name in ("config.json", "model.safetensors", "train_config.json"):
        assert (model_dir / name).is_file(), sorted(p.name for p in model_dir.parent.rglob("*"))
    assert json.loads((model_dir / "config.json").read_text())["type"] == "act"
    last = tmp_path / "outputs" / "act_lift" / "checkpoints" / "last" / "pretrained_model"
    policy = ACTPolicy.from_pretrained(str(last))
    assert set(policy.config.image_features) == {"observation.images.front", "observation.images.wrist"}
    preprocessor, postprocessor = make_pre_post_processors(policy.config, pretrained_path=str(last))
    frame = open_dataset(exported["out"], "test/lift")[0]
    batch = {k: v.unsqueeze(0) if isinstance(v, torch.Tensor) else v for k, v in frame.items()
             if k.startswith("observation.")}
    policy.eval()
    with torch.no_grad():
        action = postprocessor(policy.select_action(preprocessor(batch)))
    assert tuple(action.shape) == (1, 8) and torch.isfinite(action).all()  # 7 joints + gripper


def test_cli_help_names_every_flag():
    result = run_main("export", "--help")
    assert result.returncode == 0
    for flag in ("--out", "--repo-id", "--cameras", "--image-size", "--action", "--task", "--only-success",
                 "--no-video", "--vcodec", "--append", "--workers", "--ray"):
        assert flag in result.stdout
    info = json.dumps(result.stdout)
    assert "joint" in info and "ee_delta" in info and "ee_pose" in info


def test_ctrl_c_keeps_the_saved_episodes(recorded, tmp_path):
    """A real SIGINT after the first saved episode: finalize still runs and that episode loads."""
    import signal

    def interrupt(episodes: int, frames: int) -> None:
        if episodes == 1:
            signal.raise_signal(signal.SIGINT)  # to this (the main) thread, as a terminal's Ctrl-C reaches Python

    out = tmp_path / "ds"
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)  # as in a terminal, even under nohup
    try:
        summary = export_dataset([recorded["dir"]], ExportOptions(out=out, repo_id="t/int", cameras=["front"],
                                                                   image_size=(32, 32), progress=False,
                                                                   on_episode=interrupt))
    finally:
        signal.signal(signal.SIGINT, previous)
    assert summary.interrupted and summary.episodes == 1
    assert "interrupted" in summary.line()
    ds = open_dataset(out, "t/int")
    assert ds.num_episodes == 1 and ds.num_frames == load_episode(recorded["files"][0]).steps
    assert ds[ds.num_frames - 1]["observation.images.front"].std() > 0.05


def test_a_cancel_token_stops_the_export_keeping_the_saved_episodes(recorded, tmp_path):
    """How `teleop export` takes Ctrl-C (teleop/cli/signals.py sets the token): the export ends at the next
    frame after it is set, the saved episode is finalized and loads."""
    import threading

    token = threading.Event()

    def cancel_after_the_first(episodes: int, frames: int) -> None:
        if episodes == 1:
            token.set()

    out = tmp_path / "ds"
    summary = export_dataset([recorded["dir"]], ExportOptions(out=out, repo_id="t/cancel", cameras=["front"],
                                                               image_size=(32, 32), progress=False,
                                                               on_episode=cancel_after_the_first), cancel=token)
    assert summary.interrupted and summary.episodes == 1 and summary.dataset_episodes == 1
    ds = open_dataset(out, "t/cancel")
    assert ds.num_episodes == 1 and ds.num_frames == load_episode(recorded["files"][0]).steps
