"""What the lobby holds of a running session, wherever it runs: what it reads of the files a session
writes (its typed status file, SessionStatus, and its log), and the private files it makes for them.
A session process here (sessions.LiveSession) and one a Ray actor runs (ray_sessions.RaySession) share these.

A session binds port 0 and reports the port it got in its status file, so no other program can take
a port between the lobby choosing it and the session binding it.
"""

from __future__ import annotations

import os
import time
from pathlib import Path
from typing import IO

from teleop.campaign.operator_session import SessionSpec, SessionStatus


def private_folder(folder: Path) -> Path:
    """`folder`, made if need be, with its owner alone allowed in (mode 0700)."""
    folder.mkdir(parents=True, exist_ok=True)
    os.chmod(folder, 0o700)
    return folder


def open_private_log(path: Path) -> IO[str]:
    """A session's log file, new and readable by its owner only (0600)."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    os.fchmod(fd, 0o600)
    return os.fdopen(fd, "w")


class SessionFiles:
    """What the lobby reads of a session from the files it writes (its status file and its log), for a
    session process here (LiveSession) and one a Ray actor runs (ray_sessions.RaySession) alike."""

    spec: SessionSpec
    log_path: Path
    started: float
    ended_at: float | None
    known_live: bool = True  # what `live` found when last asked: read under locks, where `live` may block (Ray)

    @property
    def id(self) -> str:
        return self.spec.session

    @property
    def live(self) -> bool:
        raise NotImplementedError

    @property
    def minutes(self) -> float:
        """Minutes from its start to its end (to now until `live` has seen it end)."""
        end = self.ended_at if self.ended_at is not None else time.monotonic()
        return (end - self.started) / 60.0

    def status(self) -> SessionStatus | None:
        """The session's own status (None before its first write)."""
        return SessionStatus.read(self.spec.status_file)

    @property
    def port(self) -> int:
        """The port the session listens on, from its status (0 until it has written one)."""
        status = self.status()
        return status.port if status is not None else 0

    def ready(self) -> bool:
        status = self.status()
        return status is not None and status.tick > 0 and status.port > 0 and self.live

    def last_log_line(self) -> str:
        try:
            lines = [line for line in self.log_path.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            return ""
        return lines[-1][:300] if lines else ""
