"""Issue 12: annotate source demos, generate many from a few, locally and on Ray.

Sources are the scripted demos in scenes/scripts, recorded through the public API
with seeds 0 and 1; generation uses new seeds (from 1000), so nothing is re-run.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from tests.support import alive as _alive, descendants_of as _descendants

import mujoco
import numpy as np
import pytest

import teleop
from replay.subtasks.sidecar import read_subtasks, sidecar_path
from replay.subtasks.annotate import auto_subtasks
from teleop.generate.generator import GenerateError, GenerateOptions, generate
from tests.support import ROOT, assert_one_line_error, run_cli, run_json, run_main, write_script

SCRIPTS = {"lift": "lift_pick.json", "pick_place": "pick_place.json", "stack": "stack_pick.json", "door": "door_push.json"}
GOALS = {"lift": 0.9, "pick_place": 0.8, "stack": 0.7}  # the success-rate goals
HZ = 30


def _record(task: str, directory: Path, seeds=(0, 1), script: Path | None = None) -> list[Path]:
    paths = []
    for seed in seeds:
        session = teleop.Session(scene=task, robot="panda", seed=seed, control_hz=HZ)
        device = teleop.ScriptDevice(script or ROOT / "scenes" / "scripts" / SCRIPTS[task])
        with teleop.Recorder(session, directory, verify="off") as rec:
            teleop.run_episode(session, [device])
        paths.extend(rec.paths)
    return paths


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> dict[str, list[Path]]:
    root = tmp_path_factory.mktemp("sources")
    return {task: _record(task, root / task) for task in SCRIPTS}


def _cube_xy(ep) -> np.ndarray:
    """Where the episode's first state puts the red cube (m, world frame)."""
    model = ep.build_model()
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, ep.state[0], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_kinematics(model, data)
    return data.xpos[model.body("cube").id][:2].copy()


def _close_steps(script: str) -> list[int]:
    """Steps at which the script commands the gripper closed (its own timing)."""
    steps = json.loads((ROOT / "scenes" / "scripts" / script).read_text())["steps"]
    t, out = 0.0, []
    for step in steps:
        if step.get("gripper") == "close":
            out.append(round(t * HZ))
        t += step["duration"]
    return out


@pytest.mark.parametrize("task", ["lift", "pick_place", "stack", "door"])
def test_auto_annotation_finds_the_scripted_boundaries(task, sources):
    for path in sources[task]:
        ep = teleop.load_episode(path)
        subtasks = auto_subtasks(ep)
        objects = [s.object for s in subtasks]
        assert objects == {"lift": ["cube"], "pick_place": ["cube", "bin"], "stack": ["cube", "cube_base"],
                           "door": ["door_handle"]}[task]
        assert subtasks[0].start == 0 and subtasks[-1].end == ep.steps
        if len(subtasks) == 2:  # the grasp ends once the fingers have closed on the cube (the script allows 0.6 s)
            (close,) = _close_steps(SCRIPTS[task])
            assert close <= subtasks[0].end <= close + round(0.6 * HZ), (subtasks, close)
            assert subtasks[1].start == subtasks[0].end


def test_annotate_cli_stores_beside_the_episode_and_inspect_shows_it(sources, tmp_path):
    src = sources["stack"][0]
    path = tmp_path / src.name
    path.write_bytes(src.read_bytes())
    assert run_cli("annotate", str(path)).returncode == 2  # not annotated yet: says so
    out = run_json("annotate", str(path), "--auto", "--json")
    (ep,) = out["episodes"]
    assert ep["by"] == "auto" and [s["object"] for s in ep["subtasks"]] == ["cube", "cube_base"]
    assert sidecar_path(path).is_file() and path.read_bytes() == src.read_bytes()  # recorded steps untouched
    shown = run_json("inspect", str(path), "--json")["subtasks"]
    assert shown == ep["subtasks"]
    assert [s.to_json() for s in read_subtasks(path)] == shown


def test_a_source_without_a_grasp_is_named(tmp_path):
    script = write_script(tmp_path / "wave.json", [{"duration": 0.5, "move": [0.0, 0.05, 0.0]}])
    (path,) = _record("lift", tmp_path / "eps", seeds=(0,), script=script)
    result = run_cli("annotate", str(path), "--auto")
    assert_one_line_error(result, path.name, "no grasp of cube")
    result = run_cli("generate", str(path), "--out", str(tmp_path / "gen"), "--num", "2", "--workers", "1")
    assert_one_line_error(result, path.name, "no grasp")
    assert not (tmp_path / "gen").exists()


@pytest.mark.parametrize("task", ["lift", "pick_place", "stack"])
def test_generation_reaches_the_goal_and_episodes_replay_exactly(task, sources, tmp_path):
    # 10 new seeds, every one tried once: the goal in tenths (bench/generate.py measures the rates over 100);
    # on 1000-1019 lift and pick_place kept 20 of 20, stack 15 (8 of its first 10)
    seeds = 10
    summary = generate(sources[task], GenerateOptions(out=tmp_path / "gen", num=seeds, seed=1000, workers=2,
                                                      max_attempts=seeds, progress=False))
    assert summary.attempts == seeds and summary.workers == 2 and summary.backend == "local"
    assert summary.success_rate >= GOALS[task], summary
    assert summary.not_bit_exact == 0
    assert len(summary.files) == summary.successes and all(Path(f).is_file() for f in summary.files)
    names = {str(p) for p in sources[task]}
    first = teleop.load_episode(summary.files[0])
    assert first.meta.source == "generated" and first.meta.success
    assert set(first.meta.source_episodes) <= names and first.meta.source_episodes
    assert first.meta.generator["name"] == "teleop.generate.generator" and first.meta.seed in summary.seeds
    assert first.meta.seed >= 1000  # a new scene, not a source's
    assert teleop.resimulate(first).bit_exact
    # carried into the new scene: the grasp happens where this seed put the cube, not where a source had it
    here = _cube_xy(first)
    assert all(np.linalg.norm(here - _cube_xy(teleop.load_episode(p))) > 1e-3 for p in sources[task])


def _generate_cli(sources: list[Path], out: Path, workers: int) -> dict:
    """`teleop generate ... --num 3 --seed 1000 --workers N --json` in a fresh process; its JSON."""
    return run_json("generate", *map(str, sources), "--out", str(out), "--num", "3", "--seed", "1000",
                    "--workers", str(workers), "--json")


@pytest.fixture(scope="module")
def lift_two_workers(sources, tmp_path_factory) -> dict:
    """Three lift episodes from seed 1000 by 2 local workers: what 1 worker and Ray must give again."""
    return _generate_cli(sources["lift"], tmp_path_factory.mktemp("w2") / "gen", 2)


def test_cli_json_and_seed_order_do_not_depend_on_workers(sources, lift_two_workers, tmp_path):
    runs = {1: _generate_cli(sources["lift"], tmp_path / "w1", 1), 2: lift_two_workers}
    for workers, out in runs.items():
        for key in ("attempts", "successes", "success_rate", "episodes_per_min", "workers", "files"):
            assert key in out
        assert out["workers"] == workers and out["successes"] == 3 and len(out["files"]) == 3
    assert runs[1]["seeds"] == runs[2]["seeds"]
    steps = {w: [teleop.load_episode(f).steps for f in r["files"]] for w, r in runs.items()}
    assert steps[1] == steps[2]


def test_on_a_local_ray_instance(sources, lift_two_workers, tmp_path):
    import ray  # the cluster extra (the test command installs it)

    ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
    try:
        summary = generate(sources["lift"], GenerateOptions(out=tmp_path / "ray", num=3, seed=1000, ray="auto",
                                                            progress=False))
        assert ray.is_initialized()
    finally:
        ray.shutdown()
    local = lift_two_workers
    assert summary.backend == "ray" and summary.workers == 2
    assert summary.successes == local["successes"] == 3 and summary.seeds == local["seeds"]
    for a, b in zip(summary.files, local["files"], strict=True):
        ea, eb = teleop.load_episode(a), teleop.load_episode(b)
        assert ea.steps == eb.steps and np.array_equal(ea.state, eb.state)  # same episode, computed elsewhere


def test_keep_failures_marks_them(tmp_path):
    # A demo that grasps and lifts only 2 cm: every generated attempt fails the lift task (5 cm).
    script = write_script(tmp_path / "low.json", [
        {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
        {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
        {"duration": 0.6, "gripper": "close"},
        {"duration": 0.6, "move": [0, 0, 0.02]},
    ])
    src = _record("lift", tmp_path / "src", seeds=(0,), script=script)
    result = run_cli("generate", str(src[0]), "--out", str(tmp_path / "gen"), "--num", "1", "--max-attempts", "2",
                     "--keep-failures", "--workers", "1", "--json")
    assert result.returncode == 1, result.stderr  # fewer kept than asked: not a success
    out = json.loads(result.stdout)
    assert out["successes"] == 0 and out["attempts"] == 2 and out["failures_kept"] == 2
    failed = sorted((tmp_path / "gen" / "failures").glob("*.mcap"))
    assert len(failed) == 2 and not list((tmp_path / "gen").glob("*.mcap"))
    assert not teleop.load_episode(failed[0]).meta.success
    assert "stopped after 2 attempts" in out["stopped_early"]


@pytest.mark.parametrize("case", ["mixed", "num", "address", "workers"])
def test_bad_input_is_one_line_and_exit_2(case, sources, tmp_path):
    out = ["--out", str(tmp_path / "gen")]
    argv = {
        "mixed": ["generate", str(sources["lift"][0]), str(sources["stack"][0]), *out, "--num", "2"],
        "num": ["generate", str(sources["lift"][0]), *out, "--num", "0"],
        "address": ["generate", str(sources["lift"][0]), *out, "--num", "2", "--ray", "127.0.0.1:1"],
        "workers": ["generate", str(sources["lift"][0]), *out, "--num", "2", "--workers", "0"],
    }[case]
    needle = {"mixed": "one scene", "num": "positive", "address": "127.0.0.1:1", "workers": "workers"}[case]
    t0 = time.monotonic()
    # the unreachable cluster in a fresh process (Ray's client must not linger in this one); the rest in this one
    result = run_cli(*argv, timeout=120) if case == "address" else run_main(*argv)
    assert_one_line_error(result, needle)
    assert time.monotonic() - t0 < 60
    assert result.stdout == ""


def test_bad_input_from_python_raises_the_root_error(sources, tmp_path):
    with pytest.raises(teleop.TeleopError):
        generate(sources["lift"], GenerateOptions(out=tmp_path / "g", num=-1))
    with pytest.raises(GenerateError, match="one scene"):
        generate([sources["lift"][0], sources["door"][0]], GenerateOptions(out=tmp_path / "g", num=1))


def test_ctrl_c_keeps_what_was_generated(sources, tmp_path):
    """Ctrl-C in a terminal (SIGINT to the process group): exit 130, kept episodes whole, no traceback."""
    out = tmp_path / "gen"
    proc = subprocess.Popen([sys.executable, "-m", "teleop", "generate", *map(str, sources["lift"]), "--out", str(out),
                             "--num", "500", "--workers", "2"], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, start_new_session=True,
                            # as from a terminal, even when the tests themselves run with SIGINT ignored (nohup, &)
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and len(list(out.glob("*.mcap"))) < 2:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
        os.killpg(proc.pid, signal.SIGINT)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.communicate()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" in stdout
    kept = sorted(out.glob("*.mcap"))
    assert len(kept) >= 2 and not list(out.glob("*.part"))
    for path in kept:
        ep = teleop.load_episode(path)
        assert ep.meta.complete and ep.meta.success and not ep.truncated






def test_kill_9_leaves_no_orphans(sources, tmp_path):
    """Issue 24: `teleop generate --workers 2` killed by SIGKILL mid-run: within 5 s none of its children
    (the workers, the fork server they were forked from, multiprocessing's resource tracker) is left running."""
    out = tmp_path / "gen"
    proc = subprocess.Popen([sys.executable, "-m", "teleop", "generate", *map(str, sources["lift"]), "--out", str(out),
                             "--num", "500", "--workers", "2"], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, start_new_session=True)
    children: dict[int, str] = {}
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and not list(out.glob("*.mcap")):  # mid-run: the workers are busy
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
        children = _descendants(proc.pid)
        assert len(children) >= 3, children  # two workers, the resource tracker (and the fork server, if any)
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(_alive(p, s) for p, s in children.items()):
            time.sleep(0.1)
        left = [p for p, s in children.items() if _alive(p, s)]
        assert not left, f"still running 5 s after the kill: {left}"
    finally:
        for pid, started in children.items():
            if _alive(pid, started):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
