"""A session: a robot in a task scene at a fixed control rate, driven by Commands.

The session builds the scene for a seed and the `Controller` that runs its
ticks, and turns episode events from devices (start, save, discard, reset) into
calls on an attached recorder. What the tick knows (model, data, arms, poses,
success: the read-only `devices.view.SessionView` devices get) is asked of
`session.controller`, which a reset replaces; counts and operator notes that
outlive resets are `session.stats`. Recording is the Recorder's business; the
loop that polls devices and paces ticks is `teleop.control.loop.run_episode`.
`AttachedRecorder` names what the session asks of `teleop.control.recording.Recorder`,
so that this module need not import that one (which imports this one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Protocol

import numpy as np

from devices.command import Command
from scenes import RobotSpec, Scene, build_scene, load_robot
from scenes.tasks.registry import Task, find_task
from scenes.vary.variation import Variation
from teleop.control.controller import ControlStats, Controller, StepResult, TickObserver, physics_split
from teleop.errors import SessionError


class AttachedRecorder(TickObserver, Protocol):
    """What the session calls on its recorder (the Recorder attaches itself): episode events and ticks."""

    @property
    def recording(self) -> bool:
        """An episode is open."""
        ...

    def start(self) -> None: ...

    def save(self, complete: bool = True) -> list[Path]:
        """Close the open episode; its files."""
        ...

    def discard(self) -> None: ...


class Session:
    """A robot in a task scene, driven by Commands at `control_hz` ticks per second.

    scene: a task name (`teleop scenes`), a task file PATH.toml or a Task; robot: a built-in name, a PATH.toml or
    a RobotSpec; seed: object placement (same seed, same scene); control_hz:
    control ticks per second (physics runs in equal steps of at most 2 ms); variation: physics
    drawn for each seed into its model (scenes.vary.physics), recorded with every episode;
    fresh_episodes: every episode starts from its seed's initial state and a saved or discarded one
    moves the scene to the next seed (off: the scene stays where the last episode left it).
    """

    def __init__(
        self,
        scene: str | Path | Task = "lift",
        robot: str | Path | RobotSpec = "panda",
        seed: int = 0,
        control_hz: float = 30.0,
        variation: Variation | None = None,
        fresh_episodes: bool = False,
    ) -> None:
        if not (math.isfinite(control_hz) and 0 < control_hz <= 1000):
            raise SessionError(f"control rate must be between 0 and 1000 Hz, got {control_hz}")
        self.task = find_task(scene)  # a task file is read once, not at every reset
        self.scene_name = self.task.name
        self.robot = robot if isinstance(robot, RobotSpec) else load_robot(robot)
        self.control_hz = float(control_hz)
        self.dt = 1.0 / self.control_hz  # s per control tick
        self.substeps, self.timestep = physics_split(self.control_hz)
        self.stats = ControlStats()  # IK failures, clamped targets, ignored commands, notes: kept across resets
        self.recorder: AttachedRecorder | None = None
        self.variation = variation
        # Every episode from its seed's initial state: a start after the arm was driven reloads the seed, and a save
        # or discard moves to the next seed (`teleop serve` and campaigns; `teleop serve --keep-scene` turns it off).
        self.fresh_episodes = bool(fresh_episodes)
        self.load(seed)

    # --- scene lifecycle -----------------------------------------------------

    def load(self, seed: int) -> None:
        """Build the scene for `seed` (a new model: object placement is part of it)."""
        self.seed = int(seed)
        self.scene: Scene = build_scene(self.task, self.robot, self.seed, timestep=self.timestep, variation=self.variation)
        self.robot = self.scene.robot  # a user's robot gets its reach measured here
        try:
            self.controller = Controller(self.scene, self.control_hz, self.stats)  # the tick; a new one per scene
        except ValueError as exc:
            raise SessionError(str(exc)) from None

    def restore(self) -> None:
        """Back to the current seed's initial state: the same compiled model, a fresh tick on it (a new
        Controller and MjData: a new scene's, without compiling one, so pages and cameras keep their model)."""
        try:
            self.controller = Controller(self.scene, self.control_hz, self.stats)
        except ValueError as exc:
            raise SessionError(str(exc)) from None

    def reset(self, seed: int | None = None) -> None:
        """New episode layout: the next seed unless one is given. Saves a recording in progress first."""
        if self.recorder is not None and self.recorder.recording:
            self.recorder.save()
        self.load(self.seed + 1 if seed is None else seed)

    def attach(self, recorder: AttachedRecorder) -> None:
        """Let `recorder` observe the ticks (one at a time)."""
        if self.recorder is not None and self.recorder is not recorder:
            raise SessionError("the session already has a recorder attached")
        self.recorder = recorder

    def detach(self, recorder: AttachedRecorder) -> None:
        if self.recorder is recorder:
            self.recorder = None

    def close(self) -> list[Path]:
        """End the session; an episode in progress is kept, marked incomplete. Returns its files."""
        if self.recorder is not None and self.recorder.recording:
            return self.recorder.save(complete=False)
        return []

    # --- the tick ------------------------------------------------------------

    def step(self, commands: Sequence[Command] = (), ctrl: np.ndarray | None = None) -> StepResult:
        """One control tick. Episode events in the commands act first, so "start"
        records this tick.
        `ctrl` (nu joint and gripper targets) drives the tick instead of IK.
        When the events began a new scene (the next seed, or this one from its initial state), the tick's
        commands and `ctrl` are not applied: they were read against the old scene (a policy's or a leader
        arm's absolute targets would move the arm from its initial pose in one tick), so the scene's first
        step holds its initial pose; from the next tick devices drive it, those that play from their start
        restarted (the browser session restarts `Restartable` devices: a leader arm eases in)."""
        events: tuple[str, ...] = ()
        for command in commands:
            if command.events:  # most ticks carry none
                events += tuple(command.events)
        if events:
            before = self.controller
            for event in events:
                self.handle_event(event)
            if self.controller is not before:
                commands, ctrl = (), None
        recorder = self.recorder
        observer = recorder if recorder is not None and recorder.recording else None
        result = self.controller.step(commands, observer, ctrl)
        result.events = events
        return result

    def starting_episode(self) -> None:
        """Called just before the recorder opens an episode (a campaign reserves the episode's file index here)."""

    def handle_event(self, event: str) -> None:
        """start / save / discard go to the recorder (a note if there is none), record is start or save
        as the recorder stands; reset loads the next seed. With `fresh_episodes`, a start after the scene
        was stepped reloads its seed first, and an episode saved or discarded moves to the next seed."""
        if event == "reset":
            self.reset()
            return
        if event not in ("start", "save", "discard", "record"):
            return
        recorder = self.recorder
        was_recording = recorder is not None and recorder.recording
        if event == "record":  # one button: start, or save the episode being recorded
            event = "save" if was_recording else "start"
        if recorder is None:
            if event == "start":
                self.stats.note("not recording: the session has no recorder (start it with a record directory)")
            return
        if event == "start":
            if not was_recording:
                if self.fresh_episodes and self.controller.data.time > 0:
                    self.restore()  # stepped since the scene loaded: the episode starts from the seed's initial state
                self.starting_episode()
            recorder.start()
        elif event == "save":
            recorder.save()
        else:
            recorder.discard()
        if self.fresh_episodes and was_recording and not recorder.recording:
            self.reset()  # saved or discarded: the next episode gets the next seed
