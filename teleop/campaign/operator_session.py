"""One operator's session in a campaign: a Session that takes its seeds from the campaign's ledger.

What differs from `teleop serve`'s Session:
- every seed comes from `out/.campaign/seeds-<task>.txt` (ledger.next_seed), so no
  two episodes of a task share one, whoever records them and however often the
  campaign restarts;
- saving or discarding an episode resets the scene to the operator's next seed, and
  an episode started after the arm was driven around starts from its seed's
  initial state again (the scene is rebuilt for the same seed first): every episode
  starts where its seed puts the robot and the objects;
- when the task has all the successful episodes it wants, that reset moves the operator
  on to the task that still wants the most (among those the same robot, rate, physics
  and format can record in this process; if none, the page says to join again);
- the recorder stamps `operator`, `campaign` and `session` into every episode, and each
  episode's file index is reserved in the ledger too (sessions share out/<task>/).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
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
    port: int
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

    def handle_event(self, event: str) -> None:
        recorder = self.recorder
        was_recording = recorder is not None and recorder.recording
        if recorder is not None and not was_recording and event in ("start", "record") \
                and self.controller.data.time > 0:
            self.load(self.seed)  # driven since the scene loaded: the episode starts from the seed's initial state
        if recorder is not None and not was_recording and event in ("start", "record"):
            recorder.next_index = self._indices(self.campaign_task)  # type: ignore[attr-defined] - the Recorder's
        super().handle_event(event)
        if was_recording and recorder is not None and not recorder.recording and event != "reset":
            self.reset()  # saved or discarded: the next episode gets the next seed
