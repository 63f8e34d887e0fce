"""A full disk (or any write error) while recording ends the episode cleanly, in every format.

Each test records onto a small file system it makes: a tmpfs when the tests run
as root (the disk really fills up), otherwise an ordinary directory with
RLIMIT_FSIZE set on the recording process (writes past the limit fail with
EFBIG once SIGXFSZ is ignored). `teleop run` must then print one line naming the
file and the cause and exit 2; the cut file must still open; the episodes saved
before it must load and replay exactly. The browser session keeps driving.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support import CAUSES, ROOT, SmallFs, run_cli, run_json, small_fs, wait_until

SCRIPT = ROOT / "scenes" / "scripts" / "lift_pick.json"  # 144 steps; one episode is ~135 KB MCAP, ~600 KB HDF5
FAILED_FILE = re.compile(r"(/\S+/episode_(\d{6})\.(mcap|hdf5)): ")
# tmpfs size: room for two whole episodes but not three. File size limit: half an episode's file.
TMPFS_KB = {"mcap": 330, "hdf5": 1500, "both": 1850}
FILE_LIMIT = {"mcap": 64_000, "hdf5": 300_000, "both": 300_000}


def teleop_run(fs: SmallFs, fmt: str, episodes: int, limited: bool = True) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run(
        [sys.executable, "-m", "teleop", "run", "--device", f"script:{SCRIPT}", "--record", str(fs.path),
         "--format", fmt, "--episodes", str(episodes)],
        capture_output=True, text=True, timeout=600, env=env, cwd=ROOT,
        preexec_fn=fs.preexec() if limited else None,
    )


def episode_files(directory: Path) -> dict[int, list[Path]]:
    out: dict[int, list[Path]] = {}
    for p in sorted(directory.glob("episode_*.*")):
        out.setdefault(int(p.stem.split("_")[1]), []).append(p)
    return out


def digest(paths: list[Path]) -> list[str]:
    return [hashlib.sha256(p.read_bytes()).hexdigest() for p in paths]


@pytest.mark.parametrize("fmt", ["mcap", "hdf5", "both"])
def test_run_on_a_full_disk_stops_with_one_line_and_keeps_every_episode(tmp_path, fmt):
    suffixes = {"mcap": [".mcap"], "hdf5": [".hdf5"], "both": [".hdf5", ".mcap"]}[fmt]
    with small_fs(tmp_path, TMPFS_KB[fmt], FILE_LIMIT[fmt]) as fs:
        before: dict[int, list[str]] = {}
        if fs.file_limit is not None:  # a size limit fails every episode at once: record an earlier one first
            first = teleop_run(fs, fmt, 1, limited=False)
            assert first.returncode == 0, first.stderr
            before = {i: digest(ps) for i, ps in episode_files(fs.path).items()}
        result = teleop_run(fs, fmt, 4)

        # One line naming the file and the cause, exit 2, no traceback, no crash.
        assert result.returncode == 2, f"exit {result.returncode}: {result.stderr[-3000:]}"
        assert "Traceback" not in result.stderr and "Exception ignored" not in result.stderr
        lines = [line for line in result.stderr.splitlines() if line.strip()]
        assert len(lines) == 1, result.stderr
        match = FAILED_FILE.search(lines[0])
        assert match and Path(match.group(1)).parent == fs.path, lines[0]
        assert any(cause in lines[0] for cause in CAUSES), lines[0]
        cut = int(match.group(2))

        files = episode_files(fs.path)
        assert max(files) == cut, f"files after the failing episode: {files}"
        complete = [i for i in files if i < cut]
        assert complete, "no episode was completed before the disk filled up"
        for i, digests in before.items():
            assert digest(files[i]) == digests, f"episode {i} changed"

        # Episodes saved before the failure: whole, and they replay exactly.
        for i in complete:
            assert [p.suffix for p in files[i]] == suffixes
            for path in files[i]:
                info = run_json("inspect", "--json", str(path))
                assert info["complete"] and not info["truncated"] and info["steps"] == 144, info
            verify = run_json("replay", "--verify", "--json", str(files[i][0]))
            assert verify["bit_exact"] and verify["compared"] == 143, verify

        # The cut episode: every file of it that exists opens, and says it is not whole.
        assert files[cut], "the cut episode left no file"
        for path in files[cut]:
            done = run_cli("inspect", "--json", str(path))
            assert done.returncode == 0, f"{path.name}: {done.stderr[-2000:]}"
            info = json.loads(done.stdout)
            assert not info["complete"] and (info["truncated"] or not info["success"]), info
            assert 0 <= info["steps"] <= 144, info  # cut while closing: every step, but no clean end


def test_hdf5_cut_file_keeps_its_flushed_rows_and_an_honest_count(tmp_path):
    """A write that fails half way leaves the HDF5 file as it was at its last flush, num_samples included.

    The premise, a flush before the disk fills, is made to hold whatever the machine's speed: the disk fills only
    once rows are seen flushed (a quick machine once filled a fixed small disk before the first flush)."""
    import h5py

    from recorder import RecorderError
    from teleop import Recorder, Session
    from teleop.control.loop import run_episode

    def flushed_rows(path: Path) -> int:
        """num_samples as the file on disk says it (0 while the first flush is under way)."""
        try:
            with h5py.File(path, "r", locking=False) as f:
                return int(f["data/demo_0"].attrs["num_samples"])
        except (OSError, KeyError):
            return 0

    with small_fs(tmp_path, 1000, 1_000_000) as fs:  # room for the file's first 256-row chunks (~470 KB)
        session = Session()
        recorder = Recorder(session, fs.path, ("hdf5",), verify="off")
        recorder.start()
        path = fs.path / "episode_000000.hdf5"
        run_episode(session, [], max_steps=30, record=False)  # the writer's first flush takes what is there
        wait_until(lambda: flushed_rows(path) > 0, 60, "rows to reach the file")
        with fs.full(path), pytest.raises(RecorderError) as failed:
            run_episode(session, [], max_steps=5000, record=False)  # flat out: rows reach the file every 0.5 s
        message = str(failed.value)
        assert "\n" not in message and "episode_000000.hdf5" in message and any(c in message for c in CAUSES), message
        with h5py.File(path, "r") as f:
            demo = f["data/demo_0"]
            n = int(demo.attrs["num_samples"])
            assert n > 0 and not demo.attrs["closed"]
            assert {demo[name].shape[0] for name in ("states", "actions", "time", "commands")} == {n}
        info = run_json("inspect", "--json", str(path))
        assert info["steps"] == n and info["truncated"] and not info["complete"]
        verify = run_json("replay", "--verify", "--json", str(path))
        assert verify["bit_exact"] and verify["compared"] == n - 1, verify


def test_serve_keeps_driving_when_the_disk_fills(tmp_path):
    """The browser session: recording stops with the reason on the panel, the loop and the arm go on."""
    from devices.gizmo import GizmoDevice
    from teleop import Command, Recorder, Session
    from teleop.web.session_page.app import WebApp
    from teleop.web.session_page.serve_options import ServeOptions

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with small_fs(tmp_path, 96, 48_000) as fs:
        session = Session()
        Recorder(session, fs.path, ("mcap", "hdf5"), verify="off", on_error="stop")
        gizmo = GizmoDevice()
        app = WebApp(session, [gizmo], [], ServeOptions(port=port), camera=False)
        try:
            with fs.limited():
                app.start()
                app.panel_device.push(Command(events=("start",)))
                pos, quat = session.controller.target_pose(0)
                deadline = time.monotonic() + 60
                i = 0
                while time.monotonic() < deadline and app.sim.snapshot.recording_error is None:
                    gizmo.push(0, pos + [0.0005 * (i % 40), 0, 0], quat)
                    i += 1
                    time.sleep(1 / 30)
                stopped = app.sim.snapshot
                # Driving goes on: the loop ticks and the arm follows the gizmo.
                for k in range(45):
                    gizmo.push(0, pos + [0.002 * k, 0, -0.001 * k], quat)
                    time.sleep(1 / 30)
                later = app.sim.snapshot
                status = app.status()
                panel_text = app.panel._episode_text(later)
        finally:
            app.close()
        error = stopped.recording_error
        assert error is not None, "the disk never filled up"
        assert not stopped.recording and not later.recording
        assert str(fs.path) in error and any(c in error for c in CAUSES), error
        assert app.sim.error is None and status["error"] is None
        assert later.tick > stopped.tick + 30 and later.sim_time > stopped.sim_time + 1.0
        assert status["ee_pos"][0][0] > pos[0] + 0.06  # the arm followed the gizmo after the error
        assert f"Recording stopped:** {error}" in panel_text
        assert any(error in note for note in status["notes"])
