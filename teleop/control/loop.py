"""The one episode loop: poll devices, step the session, pace, stop.

`teleop run`, the browser session's control thread, the bench, and the
generation and evaluation features all run ticks through `run_episode`, so
device polling, real-time pacing and the stop rules exist once.

Pacing follows an absolute schedule: short stalls (another thread holding the
GIL, a busy machine) are caught up tick by tick so simulated time keeps pace
with the wall clock; only a lag over MAX_LAG_S (a suspended laptop) is dropped
instead of stepped in a burst, and counted as a slip.
"""

from __future__ import annotations

import contextlib
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np

from devices.base import Device, InputStamped, SceneChecked
from devices.command import Command
from scenes.errors import first_line
from teleop.control.controller import StepResult
from teleop.control.session import Session

MAX_LAG_S = 1.0  # behind schedule by more than this: drop the lost time (else catch up tick by tick)

FINITE_KINDS = ("script", "generated")  # devices that run out (a script, a generated plan); people do not

# (session, the devices' commands) -> (the commands to step, a ctrl vector that replaces IK or None)
Steer = Callable[[Session, list[Command]], tuple[list[Command], "np.ndarray | None"]]

StopReason = Literal["script_end", "success", "time", "event", "stopped", "steps"]


class Pacer:
    """Sleeps each tick to an absolute real-time schedule of `period` seconds."""

    def __init__(self, period: float, stop: threading.Event | None = None) -> None:
        self.period = period
        self.stop = stop
        self.next_tick = time.perf_counter()
        self.slips = 0  # times the loop fell more than MAX_LAG_S behind and dropped the lag
        self.max_late_s = 0.0  # worst lateness of a tick against the schedule

    def wait(self) -> None:
        """Sleep until the next tick is due (at once if late)."""
        self.next_tick += self.period
        delay = self.next_tick - time.perf_counter()
        if delay > 0:
            if self.stop is not None:
                self.stop.wait(delay)
            else:
                time.sleep(delay)
            return
        self.max_late_s = max(self.max_late_s, -delay)
        if delay < -MAX_LAG_S:
            self.slips += 1
            self.next_tick = time.perf_counter()


@dataclass
class EpisodeResult:
    """What one run of the loop did."""

    success: bool  # the task's success predicate at the end
    steps: int  # control ticks run
    sim_seconds: float
    wall_seconds: float
    ik_failures: int  # ticks in which IK could not reach the target
    ee_tracking_error_mm: dict[str, float | None]  # median and max target-to-EE distance
    stopped_by: StopReason
    seed: int = 0
    files: list[Path] = field(default_factory=list)  # saved episode files, when recording
    replay_bit_exact: bool | None = None  # the recorder's check of the saved episode, if it ran


def poll_devices(
    session: Session,
    devices: Sequence[Device],
    broken: dict[str, str] | None = None,
) -> list[Command]:
    """This tick's commands from every device.

    With `broken` given, a device that raises is recorded there (name -> one
    line) and skipped from then on, so one broken device does not stop the
    others; without it the error propagates.
    """
    commands: list[Command] = []
    for device in devices:
        if broken is None:
            commands.extend(device.poll(session.controller, session.dt))
            continue
        if device.name in broken:
            continue
        try:
            commands.extend(device.poll(session.controller, session.dt))
        except Exception as exc:  # noqa: BLE001 - a device's bug must not stop the loop
            broken[device.name] = first_line(exc)
            session.stats.note(f"{device.name} stopped: {broken[device.name]}")
    return commands


def check_devices(session: Session, devices: Sequence[Device], broken: dict[str, str] | None = None) -> None:
    """Check each device that names parts of the scene against it, before the first tick.

    The error propagates (one line), or with `broken` given the device is noted there and
    skipped, as `poll_devices` does with a device that raises.
    """
    for device in devices:
        if not isinstance(device, SceneChecked) or (broken is not None and device.name in broken):
            continue
        if broken is None:
            device.check(session.controller)
            continue
        try:
            device.check(session.controller)
        except Exception as exc:  # noqa: BLE001 - one device's bad input must not stop the others
            broken[device.name] = first_line(exc)
            session.stats.note(f"{device.name} stopped: {broken[device.name]}")


def newest_input_time(devices: Sequence[Device]) -> float:
    """time.monotonic() of the newest input any stamping device handed over (0: none)."""
    return max([0.0, *(d.last_input_time for d in devices if isinstance(d, InputStamped))])


def run_episode(
    session: Session,
    devices: Sequence[Device],
    *,
    seconds: float | None = None,
    max_steps: int | None = None,
    realtime: bool = False,
    stop_on_success: bool = False,
    stop_on_script_end: bool = True,
    stop_on_events: Sequence[str] = (),
    stop: threading.Event | None = None,
    record: bool | None = None,
    broken_devices: dict[str, str] | None = None,
    guard: contextlib.AbstractContextManager | None = None,
    before_tick: Callable[[Session], None] | None = None,
    after_tick: Callable[[Session, StepResult], None] | None = None,
    pacer: Pacer | None = None,
    steer: Steer | None = None,
) -> EpisodeResult:
    """Run ticks until a stop rule fires; returns what happened.

    Stop rules: `seconds` of simulated time, `max_steps` ticks, every device
    finished (a script that ran out, when `stop_on_script_end` and every device
    can finish), the task succeeding (`stop_on_success`), an episode event in
    `stop_on_events` ("save", "discard", "reset", ...), or `stop` being set.
    With none of them the loop runs until `stop` (or Ctrl-C).

    realtime: pace ticks to the wall clock (people driving); else flat out.
    record: start an episode on the session's recorder first and save it at the
        end (default: when a recorder is attached). False leaves episodes to the
        devices' events (the browser session's buttons).
    broken_devices: when given, a device that raises is noted there and skipped
        (the browser session); otherwise its error ends the loop.
    guard, before_tick, after_tick: a lock held around each tick and hooks run
        inside it, for a loop that shares the session with other threads.
    steer: turns the devices' commands into what the tick runs, (commands, ctrl or
        None): a policy driving until the operator takes over (teleop.learn.takeover).
    """
    if seconds is not None and seconds <= 0:
        raise ValueError("seconds must be positive")
    recorder = session.recorder
    record = recorder is not None if record is None else record
    if record and recorder is None:
        raise ValueError("record=True needs a Recorder attached to the session")
    check_devices(session, devices, broken_devices)  # a script naming what the scene lacks: before anything is recorded
    if recorder is not None:
        recorder.drivers(devices)
    if record:
        recorder.start()
    can_finish = stop_on_script_end and bool(devices) and all(d.kind in FINITE_KINDS for d in devices)
    ik_before = session.stats.ik_failures
    sim0 = session.controller.time
    steps = 0
    wall0 = time.perf_counter()
    pacer = pacer if pacer is not None else (Pacer(session.dt, stop) if realtime else None)
    guard = guard if guard is not None else contextlib.nullcontext()
    tracking_start = len(session.controller.tracking_errors)
    stopped_by: StopReason = "stopped"
    while True:
        if stop is not None and stop.is_set():
            stopped_by = "stopped"
            break
        if seconds is not None and session.controller.time - sim0 >= seconds - 1e-9:
            stopped_by = "time"
            break
        if max_steps is not None and steps >= max_steps:
            stopped_by = "steps"
            break
        if can_finish and all(d.finished for d in devices):
            stopped_by = "script_end"
            break
        with guard:
            if before_tick is not None:
                before_tick(session)
            commands = poll_devices(session, devices, broken_devices)
            ctrl = None
            if steer is not None:
                commands, ctrl = steer(session, commands)
            result = session.step(commands, ctrl)
            if after_tick is not None:
                after_tick(session, result)
        steps += 1
        if stop_on_events and any(e in stop_on_events for e in result.events):
            stopped_by = "event"
            break
        if stop_on_success and session.controller.success():
            stopped_by = "success"
            break
        if pacer is not None:
            pacer.wait()
    success = session.controller.success()
    files: list[Path] = []
    bit_exact = None
    if record and recorder.recording:
        files = recorder.save(complete=True)
        if files and recorder.last_verify is not None:
            bit_exact = recorder.last_verify.bit_exact
    return EpisodeResult(
        success=success,
        steps=steps,
        sim_seconds=round(session.controller.time - sim0, 6),
        wall_seconds=round(time.perf_counter() - wall0, 6),
        ik_failures=session.stats.ik_failures - ik_before,
        ee_tracking_error_mm=session.controller.tracking_error_mm(since=tracking_start),
        stopped_by=stopped_by,
        seed=session.seed,
        files=files,
        replay_bit_exact=bit_exact,
    )

