"""What the lobby holds of a running session, wherever it runs: a free port for it, and what it reads of
the files a session writes (its status file and its log). A session process here
(sessions.LiveSession) and one a Ray actor runs (ray_sessions.RaySession) share these."""

from __future__ import annotations

import json
import socket
import time
from pathlib import Path

from teleop.campaign.operator_session import SessionSpec


def free_port(host: str) -> int:
    """A port nothing listens on now (the session binds it a moment later)."""
    with socket.socket() as s:
        s.bind((host, 0))
        return s.getsockname()[1]


class SessionFiles:
    """What the lobby reads of a session from the files it writes (its status file and its log), for a
    session process here (LiveSession) and one a Ray actor runs (ray_sessions.RaySession) alike."""

    spec: SessionSpec
    log_path: Path
    started: float
    ended_at: float | None

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

    def status(self) -> dict:
        """The session's own status file ({} before its first write)."""
        try:
            return json.loads(Path(self.spec.status_file).read_text())
        except (OSError, ValueError):
            return {}

    def ready(self) -> bool:
        return self.live and self.status().get("tick", 0) > 0

    def last_log_line(self) -> str:
        try:
            lines = [line for line in self.log_path.read_text(errors="replace").splitlines() if line.strip()]
        except OSError:
            return ""
        return lines[-1][:300] if lines else ""
