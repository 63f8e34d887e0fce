"""Issue 25: a full disk in every command that writes: one line naming the file and the cause, exit 2,
no traceback, no orphaned workers, no temporary file left, and what was complete before still usable.

Each test writes onto a real small tmpfs (tests/support.py's `small_fs`; without the right to
mount, the same helper falls back to a per-file size limit, EFBIG). A long job (generate, export) first
says in one line when the free space is clearly too small, unless --force.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

import teleop
from replay.subtasks.sidecar import read_subtasks, sidecar_path
from tests.support import CAUSES, ROOT, run_cli, run_json, small_fs

HZ = 30
os.environ["HF_HUB_OFFLINE"] = "1"  # nothing may be downloaded, ever (the commands run here inherit it)


def record_sources(directory: Path, seeds=(0, 1)) -> list[Path]:
    paths = []
    for seed in seeds:
        session = teleop.Session(scene="lift", robot="panda", seed=seed, control_hz=HZ)
        device = teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")
        with teleop.Recorder(session, directory, verify="off") as rec:
            teleop.run_episode(session, [device])
        paths.extend(rec.paths)
    return paths


@pytest.fixture(scope="module")
def sources(tmp_path_factory) -> list[Path]:
    """Two lift demos, annotated (so a generate run says nothing about annotating them)."""
    paths = record_sources(tmp_path_factory.mktemp("sources") / "lift")
    run_json("annotate", *map(str, paths), "--auto", "--json")
    return paths


FILL_CAP = 64 << 20  # bytes: the small file systems are a few hundred kB; never fill a real disk


def fill(directory: Path, leave: int = 0) -> Path:
    """Fill the file system under `directory` until a write fails (leaving about `leave` bytes); at most FILL_CAP
    bytes, so that a run where the small file system fell back to a size limit never fills the machine's disk."""
    filler = directory / "filler.bin"
    with open(filler, "wb", buffering=0) as f:
        try:
            while f.tell() < FILL_CAP:
                f.write(b"\0" * 4096)
        except OSError:
            pass
    if leave:
        os.truncate(filler, max(0, filler.stat().st_size - leave))
    return filler


def error_line(result: subprocess.CompletedProcess, *needles: str) -> str:
    """Exit 2, no traceback, one error line on stderr naming the file and the cause; that line."""
    assert result.returncode == 2, f"exit {result.returncode}: {result.stderr[-3000:]}"
    assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr, result.stderr[-3000:]
    errors = [line for line in result.stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1, result.stderr
    for needle in needles:
        assert needle in errors[0], errors[0]
    return errors[0]


def no_temporaries(directory: Path) -> None:
    left = [p for p in directory.rglob("*") if p.name.endswith((".part", ".tmp")) or ".tmp-" in p.name]
    assert not left, left


# -- generate ---------------------------------------------------------------------------------------------


def test_generate_checks_the_space_then_stops_at_a_full_disk_and_resumes(sources, tmp_path):
    with small_fs(tmp_path, 600, 400_000) as fs:
        out = fs.path / "gen"
        argv = ["generate", *map(str, sources), "--out", str(out), "--num", "12", "--seed", "1000", "--workers", "2",
                "--json"]
        # 12 episodes of ~150 KB cannot fit in 600 KB: said after the first, before the rest is done.
        checked = run_cli(*argv)
        line = error_line(checked, str(out), "not enough free space", "--force")
        summary = json.loads(checked.stdout)  # --json: the one object, with what was done and the error
        assert summary["successes"] == 1 and summary["error"] in line
        # --force: it goes on until the disk is full.
        full = run_cli(*argv, "--force")
        line = error_line(full, "episode_", "run the same command again to resume")
        assert any(c in line for c in CAUSES), line
        summary = json.loads(full.stdout)
        assert summary["error"] and summary["resumed_from"] == 1 and summary["seeds_skipped"] == [1000]
        no_temporaries(out)
        kept = sorted(out.glob("episode_*.mcap"))
        assert len(kept) == 1 + summary["successes"] >= 2
        seeds = [teleop.load_episode(p).meta.seed for p in kept]
        assert len(set(seeds)) == len(seeds)
        for path in kept:
            ep = teleop.load_episode(path)
            assert ep.meta.complete and ep.meta.success and teleop.resimulate(ep).bit_exact


def test_generate_on_ray_stops_at_a_full_disk(sources, tmp_path):
    import ray

    from recorder.disk import WriteError
    from teleop.generate.generator import GenerateOptions, generate

    with small_fs(tmp_path, 400, 300_000) as fs:
        ray.init(num_cpus=2, include_dashboard=False, logging_level="ERROR")
        try:
            with pytest.raises(WriteError) as failed:
                generate(sources, GenerateOptions(out=fs.path / "gen", num=8, seed=1000, ray="auto", progress=False,
                                                  force=True))
            deadline = time.monotonic() + 30  # the tasks in flight are cancelled: the cluster's CPUs come back
            while time.monotonic() < deadline and ray.available_resources().get("CPU", 0) < 2:
                time.sleep(0.2)
            assert ray.available_resources().get("CPU", 0) == 2
        finally:
            ray.shutdown()
        message = str(failed.value)
        assert "\n" not in message and "episode_" in message and any(c in message for c in CAUSES), message
        summary = failed.value.summary
        assert summary.error == message and summary.backend == "ray" and summary.successes >= 1
        no_temporaries(fs.path)
        for path in sorted((fs.path / "gen").glob("episode_*.mcap")):
            assert teleop.resimulate(teleop.load_episode(path)).bit_exact


# -- annotate, convert, the replay viewer's subtasks -----------------------------------------------------------


def test_annotate_on_a_full_disk(sources, tmp_path):
    with small_fs(tmp_path, 400, 200_000) as fs:
        copies = []
        for path in sources:
            copies.append(fs.path / path.name)
            shutil.copyfile(path, copies[-1])
        fill(fs.path)
        result = run_cli("annotate", *map(str, copies), "--auto", "--json")
        line = error_line(result, str(sidecar_path(copies[0])))
        assert any(c in line for c in CAUSES), line
        assert json.loads(result.stdout) == {"episodes": [], "error": line.split("error: ", 1)[1]}
        no_temporaries(fs.path)
        assert not sidecar_path(copies[0]).exists()
        (fs.path / "filler.bin").unlink()  # space again: the same command works, the episodes are untouched
        assert len(run_json("annotate", *map(str, copies), "--auto", "--json")["episodes"]) == 2
        assert read_subtasks(copies[0]) is not None


def test_convert_on_a_full_disk(sources, tmp_path):
    with small_fs(tmp_path, 400, 200_000) as fs:
        target = fs.path / "episode.hdf5"
        fill(fs.path, leave=20_000)
        result = run_cli("convert", str(sources[0]), str(target), "--to", "hdf5")
        line = error_line(result, str(target))
        assert any(c in line for c in CAUSES), line
        assert not target.exists()
        no_temporaries(fs.path)
        assert sorted(p.name for p in fs.path.iterdir()) == ["filler.bin"]


def test_replay_viewer_subtask_save_on_a_full_disk(sources, tmp_path):
    import viser

    from teleop.web.replay_page.subtasks import SubtaskPanel

    with small_fs(tmp_path, 400, 200_000) as fs:
        path = fs.path / sources[0].name
        shutil.copyfile(sources[0], path)
        episode = teleop.load_episode(path)
        server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
        try:
            panel = SubtaskPanel(server.gui, episode, episode.build_model(), 1 / HZ, lambda: 0, lambda step: None)
            panel.add_timeline()
            panel.add_folder()
            fill(fs.path)
            panel.save()
            message = panel.message
            (fs.path / "filler.bin").unlink()
            panel.save()
            saved = panel.message, panel.state
        finally:
            server.stop()
        assert message.startswith("not saved: cannot write") and str(sidecar_path(path)) in message
        assert "\n" not in message and any(c in message for c in CAUSES), message
        assert message.count(str(sidecar_path(path))) == 1
        no_temporaries(fs.path)
        assert saved[0] == "" and "saved to" in saved[1] and read_subtasks(path) is not None


# -- export -----------------------------------------------------------------------------------------------------


def _loads(root: Path) -> int:
    """Episodes in the LeRobot dataset at root, opened from its files as training opens them (and its last frame
    read). In this process: a fresh one for each look cost ~5 s of importing LeRobot and read the same files."""
    from lerobot.datasets import LeRobotDataset

    dataset = LeRobotDataset("t/x", root=root)
    assert dataset[len(dataset) - 1]["observation.images.front"].shape[-2:] == (64, 64)
    return dataset.meta.total_episodes


@pytest.fixture(scope="module")
def four(sources, tmp_path_factory) -> Path:
    """Four episodes (each source twice) to export in pieces of one."""
    root = tmp_path_factory.mktemp("four")
    for i in range(4):
        shutil.copyfile(sources[i % 2], root / f"episode_{i:06d}.mcap")
    return root


EXPORT = ["--repo-id", "t/x", "--cameras", "front", "--image-size", "64x64"]


def test_export_checks_the_space_stops_at_a_full_disk_and_resumes(four, tmp_path):
    with small_fs(tmp_path, 250, 120_000) as fs:
        out = fs.path / "ds"
        argv = ["export", str(four), "--out", str(out), *EXPORT, "--piece-episodes", "1"]
        error_line(run_cli(*argv), str(out), "not enough free space", "--force", "--resume")
        assert _loads(out) == 1  # the first piece, whole
        shutil.rmtree(out)
        shutil.rmtree(fs.path / ".ds.export")
        line = error_line(run_cli(*argv, "--force"), str(out), "--resume")
        assert any(c in line for c in CAUSES), line
        no_temporaries(fs.path)
        subprocess.run(["mount", "-o", "remount,size=4m", str(fs.path)], check=False)
        if fs.file_limit is None:  # a tmpfs: made larger, the same command with --resume finishes the dataset
            done = run_cli(*argv, "--resume")
            assert done.returncode == 0, done.stderr[-2000:]
            assert _loads(out) == 4


def test_parallel_export_on_a_full_disk_leaves_no_half_dataset(four, tmp_path):
    with small_fs(tmp_path, 250, 120_000) as fs:
        out = fs.path / "ds"
        line = error_line(run_cli("export", str(four), "--out", str(out), *EXPORT, "--workers", "2"), str(fs.path))
        assert any(c in line for c in CAUSES), line
        assert not out.exists() and not list(fs.path.iterdir()), list(fs.path.iterdir())  # removed whole


def test_append_on_a_full_disk_leaves_the_dataset_as_it_was(four, sources, tmp_path):
    with small_fs(tmp_path, 400, 200_000) as fs:
        out = fs.path / "ds"
        first = run_cli("export", str(sources[0]), "--out", str(out), *EXPORT)
        assert first.returncode == 0, first.stderr[-2000:]
        before = {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
        fill(fs.path, leave=30_000)
        line = error_line(run_cli("export", str(four), "--out", str(out), *EXPORT, "--append", "--force"),
                          str(out), "as it was")
        assert any(c in line for c in CAUSES), line
        (fs.path / "filler.bin").unlink()
        after = {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}
        assert after == before
        no_temporaries(fs.path)
        assert _loads(out) == 1
