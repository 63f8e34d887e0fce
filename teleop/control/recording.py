"""Recording a session's episodes: the `Recorder` observes ticks and owns the files.

A Recorder attaches to a Session and is called twice per tick by the
Controller (before ctrl is written, after physics); it writes each step
straight into the episode writer's next preallocated row. It owns the writers,
the episode metadata and the verification policy:

  verify="sync"        after each saved episode, re-simulate it here and check it is bit-exact
  verify="background"  the same on a worker thread (the browser session: saving never stalls the loop)
  verify="off"         no check

A write error (a full disk, a vanished directory) ends the episode at once and
keeps what was written. With on_error="raise" (scripts, `teleop run`) the
error propagates as a RecorderError; with on_error="stop" (the browser
session) recording stops, `error` holds the one-line reason, and driving goes on.
"""

from __future__ import annotations

import platform
import sys
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from datetime import datetime, timezone
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any, Literal

import mujoco

from devices.base import Device
from devices.command import Command
from recorder import EpisodeWriter, RecorderError, next_episode_index
from recorder.format import ArmMeta, EpisodeMeta
from replay import VerifyResult, verify_file
from scenes.errors import first_line
from scenes.tasks.registry import episode_extra
from scenes.vary.variation import VARIATION_KEY
from teleop.control.controller import Controller
from teleop.control.record_row import RowFiller
from teleop.control.session import Session

Verify = Literal["sync", "background", "off"]
VERIFY_MODES = ("sync", "background", "off")


def _teleop_version() -> str:
    try:
        return version("mujoco-teleop")
    except PackageNotFoundError:
        return "dev"


def arm_metas(controller: Controller) -> tuple[ArmMeta, ...]:
    """The arms as an episode file describes them (what the export's `robot_layout` reads)."""
    return tuple(
        ArmMeta(
            ee_site=a.ee_site,
            joints=tuple(a.joints),
            actuators=tuple(controller.model.actuator(i).name for i in state.ctrl_ids),
            home=tuple(float(v) for v in a.home),
            gripper_actuator=a.gripper.actuator if a.gripper else None,
            gripper_open=a.gripper.open if a.gripper else None,
            gripper_closed=a.gripper.closed if a.gripper else None,
        )
        for a, state in zip(controller.scene.arms, controller.arms)
    )


class Recorder:
    """Records the episodes of one session into `directory`, one file per format per episode.

    Use as a context manager around the episodes to record: leaving the block
    saves an episode still open (marked incomplete if the block raised) and
    detaches the recorder. `paths` lists every file saved so far.
    """

    def __init__(
        self,
        session: Session,
        directory: str | Path,
        formats: Sequence[str] = ("mcap",),
        verify: Verify = "sync",
        on_error: Literal["raise", "stop"] = "raise",
        source: str | None = None,
        provenance: Mapping[str, Any] | None = None,
    ) -> None:
        if verify not in VERIFY_MODES:
            raise ValueError(f"verify must be one of {', '.join(VERIFY_MODES)}, got {verify!r}")
        directory = Path(directory)
        if directory.exists() and not directory.is_dir():
            raise RecorderError(f"{directory}: exists and is not a directory")
        self.session = session
        self.directory = directory
        self.formats = tuple(dict.fromkeys(formats))
        self.verify: Verify = verify
        self.on_error = on_error
        self.source = source  # None: "script" when only scripts drive, else "human"
        # EpisodeMeta fields saying where generated or policy episodes came from
        # (source_episodes, generator, policy), stored in every episode recorded.
        self.provenance = dict(provenance or {})
        self.next_index: int | None = None  # the next episode's index, once (None: one past the directory's highest)
        self.devices: tuple[str, ...] = ()  # names of the devices driving, stored in each episode
        self._device_kinds: tuple[str, ...] = ()
        self.writer: EpisodeWriter | None = None
        self.paths: list[Path] = []
        self.episodes_saved = 0
        self.episodes_discarded = 0
        self.last_verify: VerifyResult | None = None
        self.verified: dict[str, bool | None] = {}  # first file of each saved episode -> bit exact (None: still checking)
        self.on_verified: Callable[[Path, VerifyResult | None], None] | None = None
        self.error: str | None = None  # the last write error, one line
        self.record_seconds = 0.0  # control-thread time spent recording (state capture, row filling, commit)
        # Who drives now, stored in every step's `control` field: CONTROL_HUMAN or CONTROL_POLICY
        # (recorder.format). None (the default): episodes have no such field. A policy session
        # that an operator can take over sets it before each tick.
        self.control: float | None = None
        self._filler: RowFiller | None = None
        self._row = None
        session.attach(self)

    # -- lifecycle ---------------------------------------------------------------
    @property
    def recording(self) -> bool:
        return self.writer is not None

    @property
    def steps(self) -> int:
        """Steps in the episode being recorded (0 when none)."""
        return self.writer.steps if self.writer is not None else 0

    def drivers(self, devices: Sequence[Device]) -> None:
        """Name the devices that drive the next episodes (stored as where the episode came from)."""
        self.devices = tuple(d.name for d in devices)
        self._device_kinds = tuple(d.kind for d in devices)

    @property
    def episode_source(self) -> str:
        if self.source is not None:
            return self.source
        kinds = self._device_kinds
        return "script" if kinds and all(k == "script" for k in kinds) else "human"

    def metadata(self, controller: Controller, index: int) -> EpisodeMeta:
        """What the episode file says about itself (the model and where it was recorded)."""
        scene, session = controller.scene, self.session
        return EpisodeMeta(
            scene=session.scene_name,
            robot=scene.robot.name,
            arms=arm_metas(controller),
            nstate=controller.nstate,
            nq=controller.model.nq,
            nv=controller.model.nv,
            nu=controller.model.nu,
            control_hz=controller.control_hz,
            timestep=controller.timestep,
            substeps=controller.substeps,
            seed=session.seed,
            task=scene.instruction,
            cameras=tuple(scene.cameras),
            model_xml=scene.xml,
            assets=dict(scene.assets),
            mujoco_version=mujoco.__version__,
            teleop_version=_teleop_version(),
            platform=platform.platform(),
            machine=platform.machine(),
            python_version=sys.version.split()[0],
            start_time=datetime.now(timezone.utc).isoformat(),
            episode_index=index,
            source=self.episode_source,
            devices=self.devices,
            records_control=self.control is not None,
            extra={**episode_extra(scene.task, session.seed), **({VARIATION_KEY: scene.variation} if scene.variation else {})},
        ).replace(**self.provenance)

    def start(self) -> None:
        """Begin an episode from the session's current state (no-op if one is open)."""
        if self.writer is not None:
            return
        controller = self.session.controller
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
            index = next_episode_index(self.directory) if self.next_index is None else self.next_index
            self.next_index = None
            meta = self.metadata(controller, index)
            self.writer = EpisodeWriter(self.directory, index, self.formats, meta)
        except OSError as exc:
            self._failed(RecorderError(f"{self.directory}: cannot start an episode: {exc.strerror or exc}"))
            return
        except RecorderError as exc:
            self._failed(exc)
            return
        self.error = None
        self._filler = RowFiller(self.writer.columns, controller.model, controller.n_arms)
        controller.tracking_errors.clear()
        controller.steps = 0

    def save(self, complete: bool = True) -> list[Path]:
        """Finish the episode in progress (success from the task predicate); returns its files."""
        writer, self.writer = self.writer, None
        if writer is None:
            return []
        try:
            paths = writer.close(success=self.session.controller.success(), complete=complete)
        except RecorderError as exc:
            self._failed(exc, writer_closed=True)
            return []
        self.episodes_saved += 1
        self.paths.extend(paths)
        if paths and complete and self.verify != "off":
            self._check(paths[0])
        return paths

    def discard(self) -> None:
        """Stop the episode in progress and delete its files."""
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.discard()
            self.episodes_discarded += 1

    def close(self) -> list[Path]:
        """Save an episode still open, marked incomplete, and detach from the session."""
        paths = self.save(complete=False) if self.writer is not None else []
        self.session.detach(self)
        return paths

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if self.writer is not None:
            self.save(complete=exc_type is None)
        self.session.detach(self)

    # -- the tick (teleop.control.controller.TickObserver) -------------------------------
    def before_ctrl(self, controller: Controller) -> None:
        writer = self.writer
        if writer is None:
            return
        t0 = time.perf_counter()
        try:
            self._row = writer.claim()
        except RecorderError as exc:
            self._failed(exc)
            return
        self._filler.capture_state(self._row, controller.data)
        self.record_seconds += time.perf_counter() - t0

    def after_physics(self, controller: Controller, commands: Sequence[Command]) -> None:
        writer = self.writer
        if writer is None or self._row is None:
            return
        t0 = time.perf_counter()
        self._filler.finish(self._row, controller.data, controller.arms, self.control)
        writer.commit(commands)  # Command objects: the writer thread turns them into dicts
        self._row = None
        self.record_seconds += time.perf_counter() - t0

    # -- internals ---------------------------------------------------------------
    def _failed(self, exc: RecorderError, writer_closed: bool = False) -> None:
        """A write error: end the episode keeping what is on disk, then raise or report."""
        writer, self.writer = self.writer, None
        self._row = None
        if writer is not None and not writer_closed:
            try:
                writer.close(success=False, complete=False)
            except RecorderError:
                pass  # the same error again: what reached the disk stays
        self.error = first_line(exc)
        self.session.stats.note(f"recording stopped: {self.error}")
        if self.on_error == "raise":
            raise exc

    def _check(self, path: Path) -> None:
        self.verified[str(path)] = None
        if self.verify == "sync":
            self._verified(path, verify_file(path, warn=False))
            return

        def work() -> None:
            try:
                result = verify_file(path, warn=False)
            except Exception:  # noqa: BLE001 - a check that cannot run is reported as unknown
                result = None
            self._verified(path, result)

        threading.Thread(target=work, name="teleop-verify", daemon=True).start()

    def _verified(self, path: Path, result: VerifyResult | None) -> None:
        self.last_verify = result
        self.verified[str(path)] = result is not None and bool(result.bit_exact)
        if result is not None and not result.bit_exact:
            self.session.stats.note(f"episode {path.name} did not replay exactly (step {result.first_divergence_step})")
        if self.on_verified is not None:
            self.on_verified(path, result)

