"""Fault figures (issue 24): long jobs killed with SIGKILL at a random time, then run again.

Each figure comes from TRIALS real `kill -9`s of a real `teleop` process, at a random
moment after its first result has landed.

Figures (`measure`):
  faults_generate_duplicate_seeds    seeds kept twice in --out after the re-run (goal 0), summed over trials
  faults_generate_orphans_after_5s   child processes of the killed generate (workers, resource tracker)
                                     still running 5 s after the kill (goal 0), summed over trials
  faults_generate_episodes_lost      kept episodes that do not load whole or do not replay bit-exact, plus
                                     episodes short of --num after the re-run (goal 0), summed over trials
  faults_export_reexported_beyond_piece
                                     episodes that were whole on disk at the kill (in finalized pieces) and
                                     were exported again by `--resume` (goal 0), summed over trials
  faults_export_resumed_equal        1.0 when every resumed dataset equals an uninterrupted export of the
                                     same episodes (frames, values, features, stats, episode order), else 0.0
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

from tests.support import alive as _alive, children_of as _children

ROOT = Path(__file__).resolve().parent.parent
TRIALS = 3
GEN_NUM = 8
EXPORT = ["--repo-id", "bench/faults", "--cameras", "front", "--image-size", "64x48", "--piece-episodes", "2",
          "--no-video"]
EXPORT_EPISODES = 6


def _env() -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "HF_HUB_OFFLINE": "1"}


def _teleop(*args: str, wait: bool = True):
    cmd = [sys.executable, "-m", "teleop", *args]
    if not wait:
        return subprocess.Popen(cmd, cwd=ROOT, env=_env(), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
    return subprocess.run(cmd, cwd=ROOT, env=_env(), capture_output=True, text=True, timeout=900)






def _kill_at_random(proc: subprocess.Popen, started: Callable[[], bool], rng: random.Random, limit_s: float = 300) -> int:
    """SIGKILL `proc` a random 0-1.5 s after `started()` first holds; the children still alive 5 s later."""
    deadline = time.monotonic() + limit_s
    while time.monotonic() < deadline and not started():
        if proc.poll() is not None:
            raise RuntimeError("the job ended before it could be killed")
        time.sleep(0.05)
    time.sleep(rng.uniform(0.0, 1.5))
    children = _children(proc.pid)
    proc.kill()
    proc.wait(timeout=30)
    time.sleep(5.0)
    left = [p for p, s in children.items() if _alive(p, s)]
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    return len(left)


def _record_sources(directory: Path, seeds) -> list[Path]:
    import teleop

    paths: list[Path] = []
    for seed in seeds:
        session = teleop.Session(scene="lift", robot="panda", seed=seed, control_hz=30)
        with teleop.Recorder(session, directory, formats=("mcap",), verify="off") as rec:
            teleop.run_episode(session, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")])
        paths.extend(rec.paths)
    return paths


def _generation(tmp: Path, rng: random.Random, trials: int) -> dict[str, float]:
    import teleop

    sources = _record_sources(tmp / "src", (0, 1))
    _teleop("annotate", *map(str, sources), "--auto")
    duplicates = orphans = lost = 0
    for trial in range(trials):
        out = tmp / f"gen{trial}"
        argv = ["generate", *map(str, sources), "--out", str(out), "--num", str(GEN_NUM), "--seed", "1000",
                "--workers", "2"]
        proc = _teleop(*argv, wait=False)
        orphans += _kill_at_random(proc, lambda: any(out.glob("episode_*.mcap")), rng)
        _teleop(*argv, "--json")
        files = sorted(out.glob("episode_*.mcap"))
        seeds = []
        for path in files:
            try:
                ep = teleop.load_episode(path)
                whole = ep.meta.complete and not ep.truncated and teleop.resimulate(ep).bit_exact
            except teleop.TeleopError:
                whole = False
            lost += not whole
            if whole:
                seeds.append(ep.meta.seed)
        duplicates += len(seeds) - len(set(seeds))
        lost += max(0, GEN_NUM - len(set(seeds)))
        print(f"  generate trial {trial}: {len(files)} kept after the re-run", file=sys.stderr)
    return {"faults_generate_duplicate_seeds": duplicates, "faults_generate_orphans_after_5s": orphans,
            "faults_generate_episodes_lost": lost}


def _whole_episodes(out: Path) -> int:
    """Episodes in the finalized (readable) episode-metadata parquet files of a killed export."""
    import pyarrow.parquet as pq

    count = 0
    for path in sorted((out / "meta" / "episodes").rglob("*.parquet")):
        try:
            count += pq.read_metadata(path).num_rows
        except Exception:  # noqa: BLE001 - no footer: the piece in progress
            continue
    return count


def _dataset(root: Path) -> tuple[dict, list[dict], dict]:
    from lerobot.datasets import LeRobotDataset

    ds = LeRobotDataset("bench/faults", root=root)
    rows = []
    for i in range(len(ds)):
        rows.append({k: (v.numpy() if hasattr(v, "numpy") else v) for k, v in ds[i].items()})
    stats = json.loads((root / "meta" / "stats.json").read_text())
    return ds.meta.info, rows, stats


def _same(a: tuple, b: tuple) -> bool:
    import numpy as np

    info_a, rows_a, stats_a = a
    info_b, rows_b, stats_b = b
    if info_a["features"] != info_b["features"] or len(rows_a) != len(rows_b) or stats_a != stats_b:
        return False
    for x, y in zip(rows_a, rows_b):
        if x.keys() != y.keys():
            return False
        for key in x:
            if isinstance(x[key], np.ndarray):
                if not np.array_equal(x[key], y[key]):
                    return False
            elif x[key] != y[key]:
                return False
    return True


def _export(tmp: Path, rng: random.Random, trials: int) -> dict[str, float]:
    from replay.export.pieces import journal_dir

    episodes = tmp / "episodes"
    _record_sources(episodes, range(EXPORT_EPISODES))
    whole = _teleop("export", str(episodes), "--out", str(tmp / "whole"), *EXPORT)
    if whole.returncode != 0:
        raise RuntimeError(whole.stderr[-2000:])
    reference = _dataset(tmp / "whole")
    again = 0
    equal = True
    for trial in range(trials):
        out = tmp / f"ds{trial}"
        manifest = journal_dir(out) / "manifest.json"

        def started() -> bool:
            try:
                return json.loads(manifest.read_text())["done"] >= 2
            except (OSError, ValueError, KeyError):
                return False

        proc = _teleop("export", str(episodes), "--out", str(out), *EXPORT, wait=False)
        _kill_at_random(proc, started, rng)
        whole_at_kill = _whole_episodes(out)
        resumed = _teleop("export", str(episodes), "--out", str(out), *EXPORT, "--resume")
        if resumed.returncode != 0:  # killed after it finished: nothing to resume
            done = EXPORT_EPISODES if "no interrupted export" in resumed.stderr else 0
        else:
            line = next((ln for ln in resumed.stderr.splitlines() if "episodes were exported" in ln), "")
            done = int(line.split(": ", 1)[1].split(" of ")[0]) if line else 0
        again += max(0, whole_at_kill - done)
        same = _same(reference, _dataset(out))
        equal = equal and same
        print(f"  export trial {trial}: {whole_at_kill} whole at the kill, resumed after {done}, "
              f"{'equal' if same else 'NOT equal'}", file=sys.stderr)
    return {"faults_export_reexported_beyond_piece": again, "faults_export_resumed_equal": 1.0 if equal else 0.0}


def measure(quick: bool = False) -> dict[str, float]:
    rng = random.Random()
    trials = TRIALS
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="teleop-bench-faults-") as tmp:
        out.update(_generation(Path(tmp), rng, trials))
        out.update(_export(Path(tmp), rng, trials))
    return out
