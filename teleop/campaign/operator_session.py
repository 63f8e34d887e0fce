"""One operator's session in a campaign: a Session that takes its seeds from the campaign's ledger.

What differs from `teleop serve`'s Session:
- every seed comes from `out/.campaign/seeds-<task>.txt` (ledger.next_seed), so no
  two episodes of a task share one, whoever records them and however often the
  campaign restarts;
- saving or discarding an episode resets the scene to the operator's next seed from the
  ledger (Session's `fresh_episodes`, as in `teleop serve`, which also rebuilds the scene
  for the same seed when an episode starts after the arm was driven around);
- when the task has all the successful episodes it wants, that reset moves the operator
  on to the task that still wants the most (among those the same robot, rate, physics
  and format can record in this process; if none, the page says to join again);
- the recorder stamps `operator`, `campaign` and `session` into every episode, and each
  episode's file index is reserved in the ledger too (sessions share out/<task>/).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

from scenes.tasks.registry import find_task
from teleop.control.session import Session


@dataclass(frozen=True)
class SessionSpec:
    """What the lobby tells a session process (as JSON on its command line)."""

    campaign: str
    session: str  # the session's id, unique in the campaign (e.g. "s3-ana")
    operator: str
    task: str  # the task's folder name under out/
    scene: str
    robot: str
    out: str  # the campaign's out/ folder
    port: int = 0  # 0: the session binds a port the system picks and reports it in its status (no race for a free one)
    host: str = "127.0.0.1"
    token: str = ""
    control_hz: float = 30.0
    vary: str | None = None
    format: str = "mcap"
    status_file: str = ""
    minutes: float = 60.0  # the session ends after this long
    wanted: int = 0  # successful episodes the task wants (the page shows progress against it)
    campaign_wanted: int = 0  # the same for the whole campaign
    # Every task of the campaign as [name, wanted, scene, robot, control_hz, vary, format], in file order.
    tasks: tuple = ()

    @property
    def record_dir(self) -> Path:
        return Path(self.out) / self.task

    @property
    def provenance(self) -> dict[str, str]:
        """The EpisodeMeta fields every episode of this session carries."""
        return {"operator": self.operator, "campaign": self.campaign, "session": self.session}

    def compatible(self) -> list[tuple[str, int, str]]:
        """(name, wanted, scene) of the tasks this session's process can switch to: the same robot,
        rate, physics variation and format as its own."""
        mine = (self.robot, float(self.control_hz), self.vary, self.format)
        return [(name, int(wanted), scene) for name, wanted, scene, robot, hz, vary, fmt in self.tasks
                if (robot, float(hz), vary, fmt) == mine]


@dataclass(frozen=True)
class SessionStatus:
    """What a session process writes to its status file (`out/.campaign/sessions/<id>.status.json`, mode 0600)
    and the lobby reads: the one type both sides use. `serve` carries the rest of `teleop serve`'s status
    (devices, camera, latencies, ...) for scripts and the bench; no token is in any of it."""

    port: int  # the port the session listens on (it binds port 0: the system's choice)
    pid: int
    tick: int  # control ticks so far: > 0 once the session serves
    wall_time: float  # time.time() of the write
    seed: int
    recording: bool
    episode_steps: int
    episodes_saved: int
    record_dir: str | None
    realtime_factor: float | None
    latency_ms: float | None
    headline: str | None
    serve: dict = field(default_factory=dict, compare=False)

    @classmethod
    def from_serve(cls, status: Mapping) -> "SessionStatus":
        """The typed status from `teleop serve`'s status dict (teleop.web.session_page.app.WebApp.status)."""
        rest = {k: v for k, v in status.items() if k not in _STATUS_FIELDS}
        return cls(port=int(status["port"]), pid=int(status["pid"]), tick=int(status["tick"]),
                   wall_time=float(status["wall_time"]), seed=int(status["seed"]), recording=bool(status["recording"]),
                   episode_steps=int(status["episode_steps"]), episodes_saved=int(status["episodes_saved"]),
                   record_dir=status.get("record_dir"), realtime_factor=status.get("realtime_factor"),
                   latency_ms=status.get("latency_ms"), headline=status.get("headline"), serve=rest)

    def to_json(self) -> str:
        return json.dumps(asdict(self), default=_plain)

    @classmethod
    def read(cls, path: str | Path) -> "SessionStatus | None":
        """The session's newest status, or None before its first write (or from a file of another shape)."""
        try:
            doc = json.loads(Path(path).read_text())
            return cls(**{k: doc[k] for k in _STATUS_FIELDS if k in doc})
        except (OSError, ValueError, TypeError, KeyError):
            return None


_STATUS_FIELDS = tuple(f.name for f in fields(SessionStatus))


def _plain(value: object) -> object:
    """numpy scalars and paths in serve's status, as JSON."""
    item = getattr(value, "item", None)
    return item() if callable(item) else str(value)


def write_private(path: str | Path, text: str) -> None:
    """Write `text` to `path` whole (through a temporary file and a rename), readable by its owner only."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        os.fchmod(f.fileno(), 0o600)  # a .tmp left by a crash keeps its old mode otherwise
        f.write(text)
    os.replace(tmp, path)


class CampaignSession(Session):
    """A Session on campaign task `task` (its folder name) whose seeds come from `seeds(task)`, a fresh one per
    episode, reset after each save or discard; `indices(task)` reserves each new episode's file index, and
    `next_task(task)`, asked at each reset, names the (folder, scene) to move on to, or None to stay."""

    def __init__(self, task: str, seeds: Callable[[str], int], indices: Callable[[str], int],
                 next_task: Callable[[str], tuple[str, str] | None] | None = None, **kwargs) -> None:
        self.campaign_task = task
        self._seeds = seeds
        self._indices = indices
        self._next_task = next_task
        kwargs.setdefault("fresh_episodes", True)  # a reset after each save or discard, every episode from its seed's start
        super().__init__(seed=seeds(task), **kwargs)

    def reset(self, seed: int | None = None) -> None:
        """The next seed from the ledger unless one is given (saves a recording in progress first);
        the next task first if this one has all it wants."""
        if seed is None and self._next_task is not None and not (self.recorder is not None and self.recorder.recording):
            found = self._next_task(self.campaign_task)
            if found is not None and found[0] != self.campaign_task:
                self._switch(*found)
        super().reset(self._seeds(self.campaign_task) if seed is None else seed)

    def _switch(self, task: str, scene: str) -> None:
        """Record task `task` (scene `scene`) from the next reset on: its scene, folder and seeds."""
        self.task = find_task(scene)
        self.scene_name = self.task.name
        self.campaign_task = task
        recorder = self.recorder
        if recorder is not None:
            recorder.directory = Path(recorder.directory).parent / task  # type: ignore[attr-defined] - the Recorder's

    def starting_episode(self) -> None:
        """Reserve the new episode's file index in the ledger (sessions share out/<task>/)."""
        recorder = self.recorder
        if recorder is not None:
            recorder.next_index = self._indices(self.campaign_task)  # type: ignore[attr-defined] - the Recorder's
