"""A generation batch's scratch folder: a killed worker's is removed by the next process's first batch."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from teleop.generate import scratch


def dead_pid() -> int:
    """The pid of a process that has ended (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_only_the_folders_of_this_hosts_ended_processes_are_swept(tmp_path: Path):
    host = socket.gethostname()
    gone = dead_pid()
    made = {
        "dead": tmp_path / f"{scratch.PREFIX}{gone}@{host}-abcd1234",
        "mine": tmp_path / f"{scratch.PREFIX}{os.getpid()}@{host}-abcd1234",
        "parent": tmp_path / f"{scratch.PREFIX}{os.getppid()}@{host}-abcd1234",  # alive
        "other_host": tmp_path / f"{scratch.PREFIX}{gone}@not-{host}-abcd1234",
        "old_name": tmp_path / f"{scratch.PREFIX}abcd1234",  # no owner in the name: left alone
    }
    for path in made.values():
        path.mkdir()
        (path / "episode_000000.mcap.part").write_bytes(b"x" * 100)
    (tmp_path / f"{scratch.PREFIX}{gone}@{host}-file").write_text("a file, not a folder")
    removed = scratch.sweep_stale(tmp_path)
    assert removed == [made["dead"]]
    assert not made["dead"].exists()
    assert all(made[k].exists() for k in ("mine", "parent", "other_host", "old_name"))
    assert (tmp_path / f"{scratch.PREFIX}{gone}@{host}-file").exists()


def test_a_scratch_folder_is_named_by_its_process_and_removed_after_its_batch(tmp_path: Path, monkeypatch):
    monkeypatch.setattr(scratch.tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(scratch, "_swept", False)
    stale = tmp_path / f"{scratch.PREFIX}{dead_pid()}@{socket.gethostname()}-zzzz0000"
    stale.mkdir()
    with scratch.scratch_dir() as folder:
        assert folder.parent == tmp_path and folder.is_dir()
        assert folder.name.startswith(f"{scratch.PREFIX}{os.getpid()}@{socket.gethostname()}-")
        assert not stale.exists(), "the first batch sweeps what ended processes left"
    assert not folder.exists()
