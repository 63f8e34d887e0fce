"""A generation batch's scratch folder: named by the process that made it, swept once that process is gone.

A batch records its attempts in a temporary folder and hands back the bytes of what it kept. A worker
killed mid-batch (kill -9 of `teleop generate`, a lost Ray task) never runs its cleanup, and its partial
episodes would stay in the temporary folder for good. So each folder's name says which process on which
host made it (`teleop-generate-PID@HOST-xxxxxxxx`), and every `generate` run, and the first batch of every
worker process (a Ray node's too), removes the folders of this host's processes that no longer run (this
user's only; a live or unknown owner is left).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator
from pathlib import Path

PREFIX = "teleop-generate-"

_swept = False  # this process has swept once (a worker runs many batches)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process: alive
        return True
    return True


def _owner_pid(path: Path, host: str) -> int | None:
    """The pid in a scratch folder's name when this host made it, else None."""
    rest = path.name[len(PREFIX):]
    pid, at, _ = rest.partition("@")
    if not at or not pid.isdigit() or not rest[len(pid) + 1:].startswith(f"{host}-"):
        return None
    return int(pid)


def sweep_stale(root: Path | None = None) -> list[Path]:
    """Remove the scratch folders under `root` (the temporary folder) whose process on this host is gone."""
    root = Path(root or tempfile.gettempdir())
    host, uid = socket.gethostname(), os.getuid()
    removed = []
    for path in root.glob(f"{PREFIX}*"):
        pid = _owner_pid(path, host)
        try:
            mine = path.is_dir() and path.stat().st_uid == uid
        except OSError:
            continue
        if pid is None or not mine or pid == os.getpid() or _alive(pid):
            continue
        shutil.rmtree(path, ignore_errors=True)
        removed.append(path)
    return removed


@contextlib.contextmanager
def scratch_dir() -> Iterator[Path]:
    """A new scratch folder for one batch, removed when the batch ends (and by a later sweep if it never does)."""
    global _swept
    if not _swept:
        _swept = True
        sweep_stale()
    with tempfile.TemporaryDirectory(prefix=f"{PREFIX}{os.getpid()}@{socket.gethostname()}-") as tmp:
        yield Path(tmp)
