"""bench/train_eval.sh, the loop of issue 21, run whole at toy size: sources -> generate ->
export -> lerobot-train -> teleop eval, one JSON object on stdout.

The figures themselves (success >= 0.9 / 0.8 / 0.7) are measured by the bench, not here.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.warm_cli import IGNORE_ENV, WARM

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "bench" / "train_eval.sh"


def _env(folder: Path, **sizes: str) -> dict[str, str]:
    """The script's environment; its `teleop` commands forked from the warm process (tests/warm_cli.py).
    `sizes`: the script's own variables for the counts' defaults (DEMOS, STEPS, SOURCES, EPISODES) and E2E_DIR."""
    bindir = Path(sys.executable).parent
    teleop, warm = WARM.teleop_command(folder)
    # BATCH: 8 samples a step, not the bench's 64 (two steps of ACT on 2x64 images of 96x96 took ~15 s of the CPU)
    train = WARM.script_command(folder, str(bindir / "lerobot-train"))
    ours = {"PYTHON": sys.executable, "TELEOP": teleop, "LEROBOT_TRAIN": train, "WORKERS": "0", "BATCH": "8", **sizes}
    return {**os.environ, **ours, "HF_HUB_OFFLINE": "1", **warm, IGNORE_ENV: ",".join(ours)}


def _run(cwd: Path, *args: str, **sizes: str) -> tuple[dict, str]:
    proc = subprocess.run(["bash", str(SCRIPT), *args], capture_output=True, text=True, timeout=900,
                          env=_env(cwd, **sizes), cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.strip().splitlines()
    assert len(lines) == 1, proc.stdout  # one JSON object; progress went to stderr
    return json.loads(lines[0]), proc.stderr


def test_the_recipe_runs_end_to_end_with_its_defaults_and_hand_pose_actions(tmp_path):
    """`bench/train_eval.sh stack` with no option at all, as the README prints lift's: its counts made toy-sized
    through the environment, --max-seconds and --work left to their defaults. stack's defaults, which pick_place
    shares (one branch of the script): hand targets, 3e-4 on a cosine, C = 0.1, no dropout. Then a rerun in the same
    folder redoes only what its changed settings touch."""
    task, second_object = "stack", "cube_base"
    sizes = {"DEMOS": "2", "SOURCES": "1", "STEPS": "2", "EPISODES": "1", "E2E_DIR": str(tmp_path / "e2e")}
    report, _ = _run(tmp_path, task, **sizes)
    work = tmp_path / "e2e" / "stack-d2-s1"  # the default WORK: the task, demos and sources
    assert report["task"] == task and report["demos"] == 2 and report["sources"] == 1 and report["steps"] == 2
    assert report["action"] == "ee_pose"  # the task's default: a hand target, not joint targets
    assert 0.0 <= report["success_rate"] <= 1.0 and report["ci95"][0] <= report["success_rate"] <= report["ci95"][1]
    assert report["train_seconds"] >= 0
    evaluated = json.loads((work / "eval.json").read_text())
    assert len(evaluated["per_episode"]) == 1 and evaluated["action"] == "ee_pose"  # EPISODES
    assert evaluated["max_seconds"] == 20  # the default time limit
    info = json.loads((work / "ds" / "meta" / "info.json").read_text())
    assert info["features"]["action"]["names"][:4] == ["x", "y", "z", "qw"]
    assert info["features"]["observation.environment_state"]["names"][7] == f"{second_object}.x"
    config = json.loads((work / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert config["temporal_ensemble_coeff"] == 0.1 and config["n_action_steps"] == 1  # older predictions count more
    assert report["ensemble"] == 0.1
    assert config["dropout"] == 0.0 and report["dropout"] == 0.0  # the recipe trains without dropout
    # 3e-4 falling on a cosine, as the report says
    assert report["lr"] == 3e-4 and report["schedule"] == "cosine"
    trained = json.loads((work / "train" / "checkpoints" / "last" / "pretrained_model" / "train_config.json").read_text())
    assert trained["scheduler"]["type"] == "cosine_decay_with_warmup" and trained["optimizer"]["lr"] == 3e-4
    # The objects' poses are normalized like the robot state (ACT's preset leaves ENV features raw)
    assert config["normalization_mapping"]["ENV"] == "MEAN_STD"
    # Idle frames left out: the dataset holds fewer frames than the generated episodes have steps
    assert report["drop_idle"] is True
    from replay import load_episode

    steps = sum(load_episode(p).steps for p in (work / "gen").glob("*.mcap"))
    assert 0 < info["total_frames"] < steps, (info["total_frames"], steps)
    # A rerun in the same WORK redoes the first step whose settings changed and every step after it, no other:
    # more steps train again (and evaluate), from the same data (more episodes alone redo only the evaluation: the
    # test below). The options win over the environment's counts; --work relative to where it is run from.
    generated = sorted(p.name for p in (work / "gen").glob("*.mcap"))
    report, log = _run(tmp_path, task, "--steps", "3", "--episodes", "2", "--max-seconds", "1", "--work", "e2e/stack-d2-s1",
                       **sizes)
    assert "redoing train" in log and "redoing ds" not in log and report["steps"] == 3
    evaluated = json.loads((work / "eval.json").read_text())
    assert len(evaluated["per_episode"]) == 2 and evaluated["max_seconds"] == 1
    trained = json.loads((work / "train" / "checkpoints" / "last" / "pretrained_model" / "train_config.json").read_text())
    assert trained["steps"] == 3 and sorted(p.name for p in (work / "gen").glob("*.mcap")) == generated


@pytest.mark.parametrize("args", [["lift", "--action", "cartesian"], ["no_such_task"], ["lift", "--bogus"], [], ["lift", "--steps"],
                                  ["lift", "--schedule", "linear"], ["lift", "--lr", "fast"], ["lift", "--demos", "0"],
                                  ["lift", "--ensemble", "x"], ["lift", "--drop-idle"], ["lift", "--dropout", "1.5"],
                                  ["lift", "--max-seconds", "0"], ["lift", "--max-seconds", "soon"]])
def test_bad_arguments_are_one_line_and_exit_2(tmp_path, args):
    proc = subprocess.run(["bash", str(SCRIPT), *args, "--work", str(tmp_path / "w")], capture_output=True, text=True,
                          timeout=60, env=_env(tmp_path))
    assert proc.returncode == 2, (proc.stdout, proc.stderr)
    assert proc.stdout == "" and len(proc.stderr.strip().splitlines()) == 1 and "train_eval.sh" in proc.stderr


def test_the_image_recipe_trains_on_both_cameras_and_evaluates_through_them(tmp_path):
    """--images (issue 21's item 4, run on CUDA by the bench): front and wrist at 96x96, at toy size on the CPU.
    Then a failing step: the script's last line names it."""
    report, _ = _run(tmp_path, "lift", "--images", "--demos", "2", "--sources", "1", "--steps", "2", "--episodes", "1",
                     "--max-seconds", "1", "--work", "lift")
    assert report["images"] is True and report["task"] == "lift"
    work = tmp_path / "lift"
    info = json.loads((work / "ds" / "meta" / "info.json").read_text())
    for camera in ("front", "wrist"):
        assert info["features"][f"observation.images.{camera}"]["shape"][:2] == [96, 96]
    config = json.loads((work / "train" / "checkpoints" / "last" / "pretrained_model" / "config.json").read_text())
    assert {"observation.images.front", "observation.images.wrist"} <= set(config["input_features"])
    evaluated = json.loads((work / "eval.json").read_text())
    assert evaluated["cameras"] == ["front", "wrist"] and len(evaluated["per_episode"]) == 1
    # A step that fails ends the script with one line naming it, after the tool's own words, and nothing on stdout:
    # here the evaluation (more episodes redo it alone), of a checkpoint whose weights were cut short on disk
    weights = work / "train" / "checkpoints" / "last" / "pretrained_model" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:1000])
    proc = subprocess.run(["bash", str(SCRIPT), "lift", "--images", "--demos", "2", "--sources", "1", "--steps", "2", "--episodes", "2",
                           "--max-seconds", "1", "--work", "lift"], capture_output=True, text=True, timeout=300, env=_env(tmp_path),
                          cwd=tmp_path)
    assert proc.returncode != 0 and proc.stdout == "", (proc.returncode, proc.stdout)
    assert "redoing eval" in proc.stderr and "redoing train" not in proc.stderr
    said = [line for line in proc.stderr.splitlines() if line.startswith("train_eval.sh")]
    assert said[-1] == proc.stderr.splitlines()[-1], proc.stderr[-2000:]  # the script's line comes last
    assert said[-1].startswith("train_eval.sh [lift]: evaluation failed (exit "), said[-1]
    assert sum("failed" in line for line in said) == 1, said
    assert not (work / "eval.json").exists()
