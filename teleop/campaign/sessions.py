"""The session processes of a campaign: one `python -m teleop.cli.campaign_session` per operator.

Each binds a port of its own on the lobby's host (port 0: the system's pick, reported in its
status file, so no race for a free port), gets its own token (on its stdin, never in a file or a
log) and writes a status file (operator_session.SessionStatus: port, real-time factor, latency,
episodes; mode 0600, like its log). Its
stdin is a pipe the lobby holds open: closing it ends the session gracefully, and so
does the lobby's end however it comes (the kernel closes the pipe even after a
kill -9), so no session outlives its campaign. A session that dies on its own (a
crash, a kill -9) shows as `ended`; the other sessions never notice.
"""

from __future__ import annotations

import json
import os
import secrets
import signal
import subprocess
import sys
import threading
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from teleop.campaign.file import Campaign, CampaignTask
from teleop.campaign.ledger import state_dir
from teleop.campaign.operator_session import SessionSpec
from teleop.campaign.session_files import SessionFiles, open_private_log, private_folder

READY_TIMEOUT_S = 180.0  # import + scene compile on a loaded 2-core machine
STOP_TIMEOUT_S = 30.0  # an episode in progress is saved before a session exits


@dataclass
class LiveSession(SessionFiles):
    """One operator's session process, as the lobby sees it."""

    spec: SessionSpec
    proc: subprocess.Popen = field(repr=False)
    log_path: Path
    started: float = field(default_factory=time.monotonic)
    ended_at: float | None = None

    @property
    def pid(self) -> int:
        return self.proc.pid

    @property
    def node(self) -> str:
        """Where the session runs: "local" (the lobby's machine), else a Ray node's address."""
        return "local"

    def url_host(self, asked: str) -> str:
        """The host name for the session's URLs: the one the browser used to reach the lobby."""
        return asked

    @property
    def live(self) -> bool:
        if self.proc.poll() is None:
            return True
        if self.ended_at is None:
            self.ended_at = time.monotonic()
        self.known_live = False
        return False

    def end(self) -> None:
        """Ask the session to stop (it saves an episode in progress, marked incomplete)."""
        if self.proc.stdin is not None and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()
            except OSError:
                pass

    def wait(self, timeout_s: float) -> bool:
        """Whether the process ended within `timeout_s`."""
        try:
            self.proc.wait(timeout_s)
            return True
        except subprocess.TimeoutExpired:
            return False

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)


class Sessions:
    """Starts, lists and stops the campaign's session processes (thread-safe)."""

    def __init__(self, campaign: Campaign, host: str, ray_address: str | None = None) -> None:
        self.campaign = campaign
        self.host = host
        self.ray = None
        if ray_address is not None:
            from teleop.campaign.ray_sessions import RayLauncher  # Ray: an optional extra

            self.ray = RayLauncher(ray_address)
        self.all: list[LiveSession] = []
        self._lock = threading.Lock()
        self._count = 0
        self.folder = state_dir(campaign.out) / "sessions"

    def live(self) -> list:
        """The sessions running now. Each is asked outside the lock (a Ray session's answer is a call to its
        node, which a slow node can hold for seconds): no join waits on another node."""
        with self._lock:
            every = list(self.all)
        return [s for s in every if s.live]

    def known_live(self) -> list:
        """The sessions live when last asked (see `live`), and those started since: no call, for use under locks."""
        with self._lock:
            return [s for s in self.all if s.known_live]

    def find(self, session_id: str):
        with self._lock:
            return next((s for s in self.all if s.id == session_id), None)

    def start(self, operator: str, task: CampaignTask, wanted_total: int):
        """Start a session process for `operator` on `task` (returns at once; see `wait_ready`): here,
        or as a Ray actor on one of the cluster's nodes (teleop/campaign/ray_sessions.py)."""
        private_folder(self.folder)  # logs and status files: the owner's alone
        with self._lock:
            self._count += 1
            session_id = f"s{self._count}-{secrets.token_hex(3)}"
        spec = SessionSpec(
            campaign=self.campaign.name, session=session_id, operator=operator, task=task.name, scene=task.scene,
            robot=task.robot, out=str(self.campaign.out), port=0, host=self.host,
            token=secrets.token_urlsafe(18), control_hz=task.control_hz, vary=task.vary, format=task.format,
            status_file=str(self.folder / f"{session_id}.status.json"), minutes=self.campaign.session_minutes,
            wanted=task.episodes, campaign_wanted=wanted_total,
            tasks=tuple((t.name, t.episodes, t.scene, t.robot, t.control_hz, t.vary, t.format) for t in self.campaign.tasks),
        )
        log_path = self.folder / f"{session_id}.log"
        if self.ray is not None:
            session = self.ray.start(spec, log_path)
            with self._lock:
                self.all.append(session)
            return session
        with open_private_log(log_path) as log:
            proc = subprocess.Popen([sys.executable, "-m", "teleop.cli.campaign_session"], stdin=subprocess.PIPE,
                                    stdout=log, stderr=subprocess.STDOUT, text=True,
                                    env={**os.environ, "PYTHONUNBUFFERED": "1"})
        assert proc.stdin is not None
        proc.stdin.write(json.dumps(asdict(spec)) + "\n")
        proc.stdin.flush()  # kept open: the session's lifeline
        session = LiveSession(spec, proc, log_path)
        with self._lock:
            self.all.append(session)
        return session

    def wait_ready(self, session, timeout_s: float = READY_TIMEOUT_S) -> bool:
        """Block until the session ticks (True) or ended / timed out (False; the process is then ended)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if session.ready():
                return True
            if not session.live:
                return False
            time.sleep(0.1)
        self.stop(session)
        return False

    def stop(self, session, timeout_s: float = STOP_TIMEOUT_S) -> None:
        """End one session and wait for it (SIGTERM, then SIGKILL, if it does not go)."""
        session.end()
        for sig, wait in ((None, timeout_s), (signal.SIGTERM, 10.0), (signal.SIGKILL, 10.0)):
            if sig is not None:
                session.signal(sig)
            if session.wait(wait):
                break
        session.live  # noqa: B018 - notes when it ended

    def close(self) -> None:
        """End every session (each saves its episode in progress) and wait for them all."""
        running = self.live()
        for session in running:
            session.end()
        threads = [threading.Thread(target=self.stop, args=(s,)) for s in running]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
