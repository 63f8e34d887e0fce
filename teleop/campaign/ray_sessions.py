"""Sessions on a Ray cluster (`teleop campaign --ray auto|ADDRESS`): one actor per session, one CPU each.

The actor starts the same session process as a local campaign does
(`python -m teleop.cli.campaign_session`) on its node, on a port it binds there (reported in its
status file on the shared out/), and holds its
stdin as the lifeline. The lobby stays where it was started and sends each browser to the
node's host and port. The actors belong to the lobby's Ray driver (nothing detaches), so
Ray ends them when the lobby ends, however it ends, and each session process then ends with
its actor's pipe. The campaign's out/ must be a folder every node sees (a shared file
system): episodes, seeds, status files and logs are written there, as on one machine.
"""

from __future__ import annotations

import json
import os
import signal as signals
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

from scenes.workers.cluster import ClusterError, connect_ray
from teleop.campaign.operator_session import SessionSpec
from teleop.campaign.session_files import SessionFiles, open_private_log, private_folder
from teleop.web.shared.net import is_loopback

START_TIMEOUT_S = 60.0  # an actor waits this long for a free CPU on the cluster


class SessionActor:
    """Runs on a node: one session process, and what the lobby asks of it."""

    def __init__(self) -> None:
        self.proc: subprocess.Popen | None = None

    def start(self, spec_json: str, log_path: str) -> dict:
        import ray  # on the node, in Ray's worker

        spec = json.loads(spec_json)
        asked = spec["host"]
        spec["host"] = asked if is_loopback(asked) else "0.0.0.0"  # reachable from the operators' machines
        spec["port"] = 0  # bound by the session itself, reported in its status file (no race for a free port)
        private_folder(Path(log_path).parent)
        with open_private_log(Path(log_path)) as log:
            self.proc = subprocess.Popen([sys.executable, "-m", "teleop.cli.campaign_session"], stdin=subprocess.PIPE,
                                         stdout=log, stderr=subprocess.STDOUT, text=True,
                                         env={**os.environ, "PYTHONUNBUFFERED": "1"})
        assert self.proc.stdin is not None
        self.proc.stdin.write(json.dumps(spec) + "\n")
        self.proc.stdin.flush()
        node = ray.util.get_node_ip_address()
        return {"pid": self.proc.pid, "host": spec["host"],
                "node": f"{node} {ray.get_runtime_context().get_node_id()[:8]}",
                "url_host": None if is_loopback(asked) else node}

    def poll(self) -> int | None:
        return None if self.proc is None else self.proc.poll()

    def end(self) -> None:
        if self.proc is not None and self.proc.stdin is not None and not self.proc.stdin.closed:
            try:
                self.proc.stdin.close()
            except OSError:
                pass

    def signal(self, sig: int) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(sig)

    def wait(self, timeout_s: float) -> bool:
        if self.proc is None:
            return True
        try:
            self.proc.wait(timeout_s)
            return True
        except subprocess.TimeoutExpired:
            return False


@dataclass
class RaySession(SessionFiles):
    """A session run by a SessionActor, as the lobby sees it (the same calls as sessions.LiveSession)."""

    spec: SessionSpec
    actor: object = field(repr=False)
    log_path: Path
    info: dict
    ray: object = field(repr=False)
    started: float = field(default_factory=time.monotonic)
    ended_at: float | None = None

    @property
    def pid(self) -> int:
        return int(self.info["pid"])

    @property
    def node(self) -> str:
        return str(self.info["node"])

    def url_host(self, asked: str) -> str:
        return self.info["url_host"] or asked

    @property
    def live(self) -> bool:
        if self.ended_at is not None:
            return False
        try:
            running = self.ray.get(self.actor.poll.remote(), timeout=10) is None
        except Exception:  # noqa: BLE001 - the actor or its node is gone: so is the session
            running = False
        if not running:
            self.ended_at = time.monotonic()
            self.known_live = False
        return running

    def _call(self, method: str, *args, timeout_s: float = 10.0):
        try:
            return self.ray.get(getattr(self.actor, method).remote(*args), timeout=timeout_s)
        except Exception:  # noqa: BLE001 - a lost actor has nothing left to end
            return None

    def end(self) -> None:
        self._call("end")

    def signal(self, sig: int) -> None:
        self._call("signal", sig)
        if sig == signals.SIGKILL:  # the process would not go: the actor goes too
            try:
                self.ray.kill(self.actor)
            except Exception:  # noqa: BLE001
                pass

    def wait(self, timeout_s: float) -> bool:
        done = self._call("wait", timeout_s, timeout_s=timeout_s + 10.0)
        return done is None or bool(done)


class RayLauncher:
    """Starts SessionActors on the cluster at `address` (one CPU each)."""

    def __init__(self, address: str) -> None:
        self.ray = connect_ray(address)
        self.actor_class = self.ray.remote(num_cpus=1, max_concurrency=4)(SessionActor)

    def start(self, spec: SessionSpec, log_path: Path) -> RaySession:
        actor = self.actor_class.remote()
        try:
            info = self.ray.get(actor.start.remote(json.dumps(asdict(spec)), str(log_path)), timeout=START_TIMEOUT_S)
        except Exception as exc:  # noqa: BLE001 - no free CPU in time, or the node failed
            self.ray.kill(actor)
            raise ClusterError(f"no Ray node took the session in {START_TIMEOUT_S:.0f} s "
                               f"({type(exc).__name__}); the cluster may have no free CPU") from None
        return RaySession(replace(spec, host=str(info["host"])), actor, log_path, info, self.ray)
