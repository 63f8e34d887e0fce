"""`teleop eval`: a policy trained by the real `lerobot-train` on a real export runs in the scene;
a scripted policy behind the same interface succeeds on every seed; bad input is one line, exit 2.

The trained policy is as small as training allows: two scripted lift demos at 15 Hz,
exported with one 32x32 camera, ACT trained for 2 steps on the CPU (its success rate
is whatever it is: the tests check the report and the recorded rollouts).
"""

from __future__ import annotations

import os
import sys

import numpy as np
import pytest

from tests.support import PICK, assert_one_line_error, run_cli, run_json, run_main, run_script

import lerobot  # noqa: E402,F401  (the test command installs the lerobot extra)
os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever

import teleop  # noqa: E402
from replay import load_episode  # noqa: E402
from teleop.learn.evaluate import EvalOptions, evaluate, wilson_interval  # noqa: E402
from teleop.learn.policy import Policy, PolicyMismatch, ScriptedPolicy, check_features  # noqa: E402



@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A LeRobot pretrained_model folder: 2 recorded picks -> export (front 32x32) -> lerobot-train, 2 steps."""
    root = tmp_path_factory.mktemp("eval")
    run_json("run", "--device", f"script:{PICK}", "--record", str(root / "eps"), "--control-hz", "15",
             "--episodes", "2", "--json")
    dataset = root / "ds"
    result = run_cli("export", str(root / "eps"), "--out", str(dataset), "--repo-id", "test/lift",
                     "--cameras", "front", "--image-size", "32x32")
    assert result.returncode == 0, result.stderr[-3000:]
    exe = os.path.join(os.path.dirname(sys.executable), "lerobot-train")
    argv = [exe, "--dataset.repo_id=test/lift", f"--dataset.root={dataset}", "--policy.type=act",
            "--policy.device=cpu", "--policy.push_to_hub=false", "--policy.pretrained_backbone_weights=null",
            "--steps=2", "--batch_size=2", "--num_workers=0", "--wandb.enable=false", f"--output_dir={root / 'out'}"]
    env = {**os.environ, "HF_HUB_OFFLINE": "1", "WANDB_MODE": "disabled", "CUDA_VISIBLE_DEVICES": ""}
    result = run_script(argv, env, root, 900, ignore=("WANDB_MODE", "CUDA_VISIBLE_DEVICES"))
    assert result.returncode == 0, result.stderr[-3000:]
    model = root / "out" / "checkpoints" / "last" / "pretrained_model"
    assert (model / "config.json").is_file()
    return {"model": model, "root": root}


def test_trained_policy_runs_through_teleop_eval_and_its_rollouts_replay_bit_exact(trained):
    rec = trained["root"] / "rollouts"
    report = run_json("eval", "--policy", str(trained["model"]), "--scene", "lift", "--robot", "panda",
                      "--episodes", "2", "--seed", "1000", "--max-seconds", "1", "--record", str(rec),
                      "--device", "cpu", "--json")
    # What the checkpoint implies: its camera and size, its dataset's action mode and rate.
    assert report["cameras"] == ["front"] and report["image_size"] == [32, 32]
    assert report["action"] == "joint" and report["control_hz"] == 15
    assert report["episodes"] == 2 and 0 <= report["successes"] <= 2
    assert report["success_rate"] == report["successes"] / 2
    assert report["ci95"] == pytest.approx(list(wilson_interval(report["successes"], 2)), abs=1e-6)
    per = report["per_episode"]
    assert [e["seed"] for e in per] == [1000, 1001]
    for e in per:
        assert e["steps"] >= 1 and e["seconds"] <= 1.0 + 1e-9
        assert (e["seconds_to_success"] is not None) == e["success"]
        assert e["replay_bit_exact"] is True
    times = [e["seconds_to_success"] for e in per if e["success"]]
    assert report["mean_seconds_to_success"] == (pytest.approx(sum(times) / len(times)) if times else None)

    # Every rollout is a normal episode: source policy, the policy's path, the seed; it replays bit-exact.
    files = sorted(rec.glob("*.mcap"))
    assert [str(f) for f in files] == [e["file"] for e in per]
    for f, e in zip(files, per):
        episode = load_episode(f)
        assert episode.meta.source == "policy"
        assert episode.meta.policy == str(trained["model"].resolve())
        assert episode.meta.seed == e["seed"] and episode.steps == e["steps"]
        assert teleop.resimulate(episode).bit_exact


@pytest.mark.parametrize("action", ["ee_pose", "ee_delta"])
def test_a_scripted_policy_succeeds_on_every_seed(action, tmp_path):
    """The lift script as a policy, through the env's EE actions: every seed succeeds, the report says so."""
    rec = tmp_path / "rec" if action == "ee_pose" else None
    seen = []
    policy = ScriptedPolicy(PICK)
    assert isinstance(policy, Policy)  # the one interface a LeRobot checkpoint is run through too
    summary = evaluate(policy, EvalOptions(scene="lift", robot="panda", episodes=3, seed=1000, action=action,
                                           cameras=(), max_seconds=8, record=rec, on_episode=seen.append))
    assert summary.successes == summary.episodes == 3 and summary.success_rate == 1.0
    assert [e.seed for e in summary.per_episode] == [1000, 1001, 1002] and seen == summary.per_episode
    for e in summary.per_episode:
        # Ended by success, well before the time limit, after the script's approach and grasp.
        assert e.success and 2.0 < e.seconds_to_success < 8.0 and e.steps == round(e.seconds_to_success * 30)
    lo, hi = summary.ci95
    assert hi == 1.0 and lo == pytest.approx(0.438503, abs=1e-6)
    text = "\n".join(summary.lines())
    assert "3/3 = 100.0%" in text and "95% Wilson interval 43.9-100.0%" in text and "seed 1002: success" in text
    if rec is not None:
        assert all(e.replay_bit_exact for e in summary.per_episode)
        episode = load_episode(summary.per_episode[0].file)
        assert episode.meta.source == "policy" and episode.meta.policy == "script:lift_pick.json"
        assert episode.meta.success and teleop.resimulate(episode).bit_exact


def test_wilson_interval():
    assert wilson_interval(5, 10) == pytest.approx((0.236593, 0.763407), abs=1e-6)
    assert wilson_interval(0, 50) == pytest.approx((0.0, 0.071348), abs=1e-6)
    assert wilson_interval(0, 0) == (0.0, 1.0)


def test_feature_mismatches_name_the_feature():
    env = {"observation.state": {"shape": (8,), "names": ["j1"] * 7 + ["gripper"]},
           "observation.images.front": {"shape": (32, 32, 3), "names": ["height", "width", "channels"]},
           "action": {"shape": (8,), "names": ["x", "y", "z", "qw", "qx", "qy", "qz", "gripper"]}}
    ok_in = {"observation.state": (8,), "observation.images.front": (3, 32, 32)}
    check_features(ok_in, {"action": (8,)}, env)  # images compared channel-first
    with pytest.raises(PolicyMismatch, match="observation.images.wrist"):
        check_features({**ok_in, "observation.images.wrist": (3, 32, 32)}, {"action": (8,)}, env)
    with pytest.raises(PolicyMismatch, match=r"observation.images.front has shape \[3, 64, 64\]"):
        check_features({"observation.images.front": (3, 64, 64)}, {"action": (8,)}, env)
    with pytest.raises(PolicyMismatch, match="policy feature action is j1"):  # joint-trained, ee_pose env
        check_features(ok_in, {"action": (8,)}, env, {"action": ["j1"] * 7 + ["gripper"]})


def test_a_policy_for_another_robot_is_one_line(trained):
    result = run_cli("eval", "--policy", str(trained["model"]), "--robot", "so101", "--episodes", "1")
    assert_one_line_error(result, "observation.state", "so101")


def test_the_checkpoint_reads_the_objects_state_and_another_task_cannot_supply_it(trained):
    """The export's default environment state (the cube's pose) is an input the trained ACT takes;
    a scene whose objects differ (stack: two cubes) is named in one line before torch loads."""
    import json

    config = json.loads((trained["model"] / "config.json").read_text())
    assert config["input_features"]["observation.environment_state"]["shape"] == [7]
    result = run_cli("eval", "--policy", str(trained["model"]), "--scene", "stack", "--episodes", "1")
    assert_one_line_error(result, "observation.environment_state", "stack")


def test_a_missing_folder_and_bad_episodes_are_one_line(tmp_path):
    """Through the CLI's entry point in this process (the tests above run `teleop eval` in fresh ones)."""
    assert_one_line_error(run_main("eval", "--policy", str(tmp_path / "nope")), "no such policy folder")
    assert_one_line_error(run_main("eval", "--policy", str(tmp_path)), "no config.json")
    for bad in ("0", "many"):
        assert_one_line_error(run_main("eval", "--policy", str(tmp_path), "--episodes", bad), "--episodes")


def test_a_trained_checkpoint_drives_a_served_session_until_taken_over(trained):
    """`teleop serve --policy` with the trained checkpoint: its cameras and rate, its actions as ctrl."""
    from devices.gizmo import GizmoDevice
    from teleop.control.loop import run_episode
    from teleop.learn.policy import LeRobotPolicy
    from teleop.learn.takeover import Takeover

    policy = LeRobotPolicy.load(trained["model"])
    with pytest.raises(PolicyMismatch, match="trained on 15 frames/s; the session runs at 30 Hz"):
        Takeover.for_session(teleop.Session("lift", "panda", seed=0, control_hz=30), policy)
    session = teleop.Session("lift", "panda", seed=0, control_hz=15)
    takeover = Takeover.for_session(session, policy)
    try:
        assert takeover.env.cameras == ["front"] and takeover.env.image_size == (32, 32)
        home = session.controller.data.ctrl.copy()
        gizmo = GizmoDevice()
        run_episode(session, [gizmo], max_steps=5, record=False, steer=takeover.steer)
        assert takeover.driver == "policy" and takeover.policy_steps == 5
        assert not np.array_equal(session.controller.data.ctrl, home)  # the policy's joint targets went to ctrl
        assert takeover.status()["inference_ms"] > 0 and takeover.status()["observe_ms"] > 0
        gizmo.push(0, session.controller.target_pose()[0] + [0.0, 0.03, 0.0], session.controller.target_pose()[1], "start")
        run_episode(session, [gizmo], max_steps=3, record=False, steer=takeover.steer)
        assert takeover.driver == "operator" and takeover.policy_steps == 5 and takeover.operator_steps == 3
    finally:
        takeover.close()


def test_eval_record_on_a_full_disk_is_one_line_with_the_report(trained, tmp_path):
    """Issue 25: `teleop eval --record` onto a full disk: one line naming the file and the cause, exit 2,
    the --json report of the rollouts done (with `error`), every rollout recorded before it whole."""
    import json

    from tests.support import CAUSES, small_fs

    with small_fs(tmp_path, 300, 100_000) as fs:
        rec = fs.path / "rollouts"
        if fs.file_limit is None:  # a tmpfs: room for a few rollouts (~10 KB each), not eight
            (fs.path / "filler.bin").write_bytes(b"\0" * (300 * 1024 - 40_000))
        result = run_cli("eval", "--policy", str(trained["model"]), "--scene", "lift", "--robot", "panda",
                         "--episodes", "8", "--seed", "1000", "--max-seconds", "1", "--record", str(rec),
                         "--device", "cpu", "--json")
        assert result.returncode == 2, result.stderr[-3000:]
        assert "Traceback" not in result.stderr
        errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
        assert len(errors) == 1 and str(rec) in errors[0] and any(c in errors[0] for c in CAUSES), result.stderr
        report = json.loads(result.stdout)
        assert report["error"] and report["error"] in errors[0] and report["episodes"] < 8
        assert not [p for p in fs.path.rglob("*") if p.name.endswith((".part", ".tmp"))]
        for e in report["per_episode"]:  # the rollouts recorded before the disk filled: whole, bit-exact
            episode = load_episode(e["file"])
            assert episode.meta.complete and teleop.resimulate(episode).bit_exact
