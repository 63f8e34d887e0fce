"""Issue 24 item 1: `teleop generate` run again continues where it stopped, with no duplicate seed.

Real processes and real signals: a `teleop generate --workers 2` is killed with
SIGKILL at a random point, run again with the same command, and the result is
checked: exactly --num kept episodes, no seed twice, every file whole and
replaying bit for bit, no worker left running, and the same episodes an
uninterrupted run gives.
"""

from __future__ import annotations

import os
import random
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from tests.support import alive, descendants_of

import numpy as np
import pytest

import teleop
from teleop.generate.resume import JOURNAL
from tests.support import ROOT, assert_one_line_error, run_cli, run_json, run_main

HZ = 30
NUM = 5


def record_sources(directory: Path) -> list[Path]:
    """Two scripted lift demos (seeds 0 and 1) through the public API."""
    paths = []
    for seed in (0, 1):
        session = teleop.Session(scene="lift", robot="panda", seed=seed, control_hz=HZ)
        device = teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")
        with teleop.Recorder(session, directory, verify="off") as rec:
            teleop.run_episode(session, [device])
        paths.extend(rec.paths)
    return paths


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> list[Path]:
    return record_sources(tmp_path_factory.mktemp("sources") / "lift")


def generate_argv(sources: list[Path], out: Path, *more: str) -> list[str]:
    return ["generate", *map(str, sources), "--out", str(out), "--seed", "1000", *more]






def kept_seeds(directory: Path) -> list[int]:
    """The seed of every episode file in `directory` (one per episode: .mcap)."""
    return [teleop.load_episode(p).meta.seed for p in sorted(directory.glob("episode_*.mcap"))]


def assert_whole_and_exact(directory: Path) -> None:
    for path in sorted(directory.glob("episode_*.*")):
        ep = teleop.load_episode(path)
        assert ep.meta.complete and ep.meta.success and not ep.truncated, path
        assert teleop.resimulate(ep).bit_exact, path
    assert not list(directory.glob("*.part"))


def test_kill_9_then_resume_keeps_num_episodes_without_duplicates(sources, tmp_path):
    rng = random.Random()
    out = tmp_path / "gen"
    scratch = tmp_path / "tmp"  # the workers' temporary folder: what a killed worker leaves is seen here
    scratch.mkdir()
    env = {**os.environ, "PYTHONPATH": str(ROOT), "TMPDIR": str(scratch)}
    proc = subprocess.Popen([sys.executable, "-m", "teleop", *generate_argv(sources, out, "--num", str(NUM),
                                                                                "--workers", "2")],
                            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                            start_new_session=True)
    children: dict[int, str] = {}
    try:
        at = rng.randint(1, NUM - 2)  # killed after a random number of kept episodes, plus a random delay
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline and len(list(out.glob("episode_*.mcap"))) < at:
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.05)
        time.sleep(rng.uniform(0.0, 0.6))
        children = descendants_of(proc.pid)
        proc.kill()
        proc.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and any(alive(p, s) for p, s in children.items()):
            time.sleep(0.1)
        assert not [p for p, s in children.items() if alive(p, s)], "workers left running 5 s after the kill"
    finally:
        for pid, started in children.items():
            if alive(pid, started):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()
        proc.communicate()
    before = kept_seeds(out)
    assert before and len(before) < NUM + 1

    # the workers saw the driver die and removed their batch folders; one killed with SIGKILL itself (an OOM
    # kill, a lost Ray task) cannot: its folder, made here for a process that has ended, goes with the resume
    left = sorted(p.name for p in scratch.glob("teleop-generate-*"))
    ended = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    stale = scratch / f"teleop-generate-{int(ended.stdout)}@{socket.gethostname()}-k1lled00"
    stale.mkdir()
    (stale / "episode_000003.mcap.part").write_bytes(b"\0" * 4096)
    resumed = run_json(*generate_argv(sources, out, "--num", str(NUM), "--workers", "2", "--json"),
                       env={"TMPDIR": str(scratch)})
    now = sorted(p.name for p in scratch.glob("teleop-generate-*"))
    assert not now, f"batch folders left after the resume: {now} (after the kill: {left})"
    assert resumed["resumed_from"] == len(before)
    assert set(before) <= set(resumed["seeds_skipped"])
    assert resumed["successes"] == NUM - len(before)
    assert not set(resumed["seeds"]) & set(resumed["seeds_skipped"])
    after = kept_seeds(out)
    assert len(after) == NUM and len(set(after)) == NUM, after  # exactly --num, no seed twice
    assert_whole_and_exact(out)

    # The same episodes an uninterrupted run keeps (same seeds, same names, same states).
    whole = run_json(*generate_argv(sources, tmp_path / "whole", "--num", str(NUM), "--workers", "1", "--json"))
    assert sorted(whole["seeds"]) == sorted(after)
    for name in (Path(f).name for f in whole["files"]):
        a, b = teleop.load_episode(out / name), teleop.load_episode(tmp_path / "whole" / name)
        assert a.meta.seed == b.meta.seed and np.array_equal(a.state, b.state)

    # Asked again: nothing left to do, nothing written.
    again = run_json(*generate_argv(sources, out, "--num", str(NUM), "--workers", "2", "--json"))
    assert again["resumed_from"] == NUM and again["successes"] == 0 and again["files"] == []
    assert kept_seeds(out) == after


def test_files_decide_after_a_kill_between_file_and_journal(sources, tmp_path):
    """A kill -9 after an episode's file landed but before its journal line (and between its two formats)."""
    out = tmp_path / "gen"
    first = run_json(*generate_argv(sources, out, "--num", "3", "--workers", "1", "--format", "both", "--json"))
    files = sorted(out.glob("episode_*"))
    assert len(files) == 6
    journal = out / JOURNAL
    lines = journal.read_text().splitlines()
    journal.write_text("\n".join(lines[:-2]) + "\n" + lines[-2][: len(lines[-2]) // 2])  # last line lost, one cut
    last = Path(first["files"][-1])  # the last episode's .mcap stays, its .hdf5 is gone: that seed runs again
    last.with_suffix(".hdf5").unlink()
    (out / "episode_000099.mcap.part").write_bytes(b"half")
    resumed = run_json(*generate_argv(sources, out, "--num", "3", "--workers", "1", "--format", "both", "--json"))
    assert resumed["resumed_from"] == 2 and resumed["successes"] == 1
    assert sorted(p.name for p in out.glob("episode_*")) == sorted(p.name for p in files)
    seeds = kept_seeds(out)
    assert len(seeds) == 3 == len(set(seeds)) and sorted(seeds) == sorted(first["seeds"])
    assert_whole_and_exact(out)


def test_other_sources_or_options_are_refused_in_one_line(sources, tmp_path):
    out = tmp_path / "gen"
    run_json(*generate_argv(sources, out, "--num", "1", "--workers", "1", "--json"))
    other_seed = ["generate", *map(str, sources), "--out", str(out), "--seed", "2000", "--num", "1", "--workers", "1"]
    assert_one_line_error(run_cli(*other_seed), "--seed", "--force-new")  # a fresh process; the other two in this one
    assert_one_line_error(run_main(*generate_argv(sources[:1], out, "--num", "1", "--workers", "1")), "sources")
    assert len(kept_seeds(out)) == 1  # nothing written by the refused runs

    forced = run_json(*other_seed, "--force-new", "--json")
    assert forced["resumed_from"] == 0 and forced["successes"] == 1
    assert forced["seeds"][0] >= 2000 and len(kept_seeds(out)) == 2

    # A directory with episodes that no generate run recorded there.
    stray = tmp_path / "stray"
    stray.mkdir()
    (stray / "episode_000000.mcap").write_bytes(sources[0].read_bytes())
    assert_one_line_error(run_main(*generate_argv(sources, stray, "--num", "1", "--workers", "1")), "--force-new")
    assert (stray / "episode_000000.mcap").read_bytes() == sources[0].read_bytes()
