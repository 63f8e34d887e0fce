"""The control loop of a served session: its own thread, real time, fixed rate.

Everything that changes the Session (device commands, panel buttons, reset)
runs here, between ticks, under `lock`; the lock is held only while stepping.
Each tick ends by publishing an immutable `Snapshot` (a copy of qpos and the
figures the page shows) that drawing, camera and panel threads read without
any lock, so the physics MjData is touched by nothing but ctrl and mj_step:
that is what keeps recordings exactly replayable, however many browsers watch.

The ticks run through the one episode loop (`teleop.control.loop.run_episode`),
paced to the wall clock on an absolute schedule (`teleop.control.loop.Pacer`): short
stalls are caught up, a lag over a second is dropped and counted as a slip.
Episodes start and end by the operator's events, not by the loop.
"""

from __future__ import annotations

import collections
import queue
import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field

import mujoco
import numpy as np

from devices.base import InputStamped, Restartable
from scenes.errors import first_line
from teleop.control.controller import StepResult
from teleop.control.loop import Pacer, Steer, newest_input_time, poll_devices, run_episode
from teleop.control.session import Session
from teleop.web.shared.loop_thread import LoopThread

RATE_WINDOW_S = 1.0


@dataclass(frozen=True)
class Snapshot:
    """What one tick left behind, for threads that must not touch the physics."""

    tick: int
    generation: int  # changes when reset() builds a new model
    model: mujoco.MjModel
    seed: int
    sim_time: float
    qpos: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray
    xpos: np.ndarray  # (nbody, 3) m, world frame: the bodies' poses at this tick, for drawing
    xquat: np.ndarray  # (nbody, 4) wxyz
    targets: tuple[tuple[np.ndarray, np.ndarray], ...]
    ee: tuple[tuple[np.ndarray, np.ndarray], ...]
    tracking_error_m: np.ndarray
    gripper_open: tuple[bool, ...]
    success: bool
    recording: bool
    recording_error: str | None  # why recording stopped by itself (a full disk), one line
    episode_steps: int
    episodes_saved: int
    episodes_discarded: int
    ik_failures: int
    input_time: float  # time.monotonic() when the newest applied device input arrived (0: none yet)
    published: float = field(default_factory=time.monotonic)

    def pose(self, data: mujoco.MjData) -> None:
        """Put this tick's poses into `data` (an MjData of `self.model` owned by the caller)."""
        data.qpos[:] = self.qpos
        if self.model.nmocap:
            data.mocap_pos[:] = self.mocap_pos
            data.mocap_quat[:] = self.mocap_quat
        mujoco.mj_kinematics(self.model, data)


class SimThread(LoopThread):
    """Runs `session.step` at `session.control_hz` in real time until stopped."""

    join_timeout = 5.0

    def __init__(self, session: Session, devices: list, log: Callable[[str], None] = print,
                 steer: Steer | None = None) -> None:
        self.session = session
        self.steer = steer  # a policy that drives until the operator takes over (teleop.learn.takeover)
        self.devices = list(devices)
        self.log = log
        self.lock = threading.Lock()
        self.device_problems: dict[str, str] = {}
        self._actions: queue.SimpleQueue[Callable[[Session], None]] = queue.SimpleQueue()
        self._init_thread("teleop-sim")
        self._generation = 0
        self._model = session.controller.model
        self._ticks = 0
        self._tick_times: collections.deque[float] = collections.deque()
        self._compute_s: collections.deque[float] = collections.deque(maxlen=300)
        self._input_time = 0.0
        # Key-to-tick latency: from a stamped input's arrival (devices.base.InputStamped) to the end of the tick
        # that applied it, ms (the last ones, for a median or p95).
        self.tick_latency_ms: collections.deque[float] = collections.deque(maxlen=200)
        self.on_tick: Callable[[], None] | None = None  # called (in this thread) after every tick: the drawer's cue
        # called (in this thread) after every tick with (controller, snapshot, device problems): companion pages (the XR page)
        self.tick_hooks: list[Callable[[object, Snapshot, dict], None]] = []
        self._stamped = [d for d in self.devices if isinstance(d, InputStamped)]  # checked once: a Protocol check is slow
        self._restartable = [d for d in self.devices if isinstance(d, Restartable)]
        self._devices_tick = session.controller  # the scene (its tick) the devices last started on
        self.device_restarts = 0  # times the Restartable devices began again on a new scene
        self._saved_seen = len(session.recorder.paths) if session.recorder is not None else 0
        self._tick_start = 0.0
        self.pacer = Pacer(session.dt, self._stop)
        self.sim_seconds = 0.0  # simulated time stepped by this loop (survives resets)
        self.wall_started = 0.0
        self.error: str | None = None
        self.on_saved: Callable[[list], None] | None = None  # called (in this thread) with new episode files
        self.snapshot: Snapshot = self._snapshot()

    # -- control ---------------------------------------------------------
    def start(self) -> None:
        self.wall_started = time.monotonic()
        self._thread.start()

    @property
    def alive(self) -> bool:
        return self._thread.is_alive()

    def submit(self, action: Callable[[Session], None]) -> None:
        """Run `action(session)` in the loop thread before the next tick."""
        self._actions.put(action)

    def step_once(self) -> Snapshot:
        """One tick in the caller's thread, for benches and tests (the loop must not be running)."""
        if self._thread.is_alive():
            raise RuntimeError("the control loop is running")
        with self.lock:
            self._before_tick(self.session)
            commands = poll_devices(self.session, self.devices, self.device_problems)
            ctrl = None
            if self.steer is not None:
                commands, ctrl = self.steer(self.session, commands)
            result = self.session.step(commands, ctrl)
            self._after_tick(self.session, result)
        return self.snapshot

    @property
    def slips(self) -> int:
        """Times the loop fell more than a second behind and dropped the lag."""
        return self.pacer.slips

    @property
    def max_late_s(self) -> float:
        """Worst lateness of a tick against the schedule, s."""
        return self.pacer.max_late_s

    # -- figures ---------------------------------------------------------
    def loop_hz(self) -> float:
        """Ticks in the last second (0 before the first second has passed)."""
        times = list(self._tick_times)
        if len(times) < 2:
            return 0.0
        span = times[-1] - times[0]
        return (len(times) - 1) / span if span > 0 else 0.0

    def compute_ms(self) -> float:
        """Median compute time of one tick (device polls + step + snapshot), ms."""
        values = list(self._compute_s)
        return float(np.median(values)) * 1000.0 if values else 0.0

    def headroom(self) -> float:
        """How many times faster than real time the loop could run (period / tick compute)."""
        ms = self.compute_ms()
        return (self.session.dt * 1000.0 / ms) if ms > 0 else 0.0

    def realtime_factor(self) -> float:
        wall = time.monotonic() - self.wall_started if self.wall_started else 0.0
        return self.sim_seconds / wall if wall > 0 else 0.0

    # -- the loop ----------------------------------------------------------
    def _run(self) -> None:
        self.pacer = Pacer(self.session.dt, self._stop)
        self.pacer.next_tick = time.perf_counter()
        try:
            run_episode(
                self.session, self.devices, realtime=True, pacer=self.pacer, stop=self._stop, record=False,
                stop_on_script_end=False, broken_devices=self.device_problems, guard=self.lock,
                before_tick=self._before_tick, after_tick=self._after_tick, steer=self.steer,
            )
        except Exception as exc:  # noqa: BLE001 - reported on the page and by the CLI
            self.error = f"{type(exc).__name__}: {exc}"
            self.log("control loop stopped: " + self.error)
            traceback.print_exc()
        finally:
            with self.lock:
                self._run_actions()

    def _before_tick(self, session: Session) -> None:
        self._tick_start = time.perf_counter()
        self._run_actions()

    def _after_tick(self, session: Session, result: StepResult) -> None:
        # Devices that stamp their input (the browser gizmo, keys typed in a page) let the page show
        # input-to-display latency, and the status the key-to-tick latency.
        newest = newest_input_time(self._stamped)
        if newest > self._input_time:
            self.tick_latency_ms.append((time.monotonic() - newest) * 1000.0)
            self._input_time = newest
        self.sim_seconds += session.dt
        self._ticks += 1
        self._check_saved()
        self._check_scene()
        self.snapshot = self._snapshot()
        self._compute_s.append(time.perf_counter() - self._tick_start)
        stamp = time.monotonic()
        self._tick_times.append(stamp)
        while self._tick_times and stamp - self._tick_times[0] > RATE_WINDOW_S:
            self._tick_times.popleft()
        on_tick = self.on_tick
        if on_tick is not None:
            on_tick()
        for hook in self.tick_hooks:
            try:
                hook(session.controller, self.snapshot, self.device_problems)
            except Exception as exc:  # noqa: BLE001 - a page's bug must not stop the loop
                session.stats.note(f"{type(exc).__name__}: {exc}")

    def _run_actions(self) -> None:
        while True:
            try:
                action = self._actions.get_nowait()
            except queue.Empty:
                return
            try:
                action(self.session)
            except Exception as exc:  # noqa: BLE001 - a failed button must not stop the loop
                self.session.stats.note(f"{type(exc).__name__}: {exc}")
            self._check_saved()
            self._check_scene()

    def _check_scene(self) -> None:
        """A new scene (a reset, or an episode saved, discarded or started afresh): the devices that play from
        the beginning (a script, a leader arm that eases in to the robot's pose) start again, as `teleop run`
        restarts them between episodes, before their next poll."""
        controller = self.session.controller  # a new one for a new scene, and for the same seed started afresh
        if controller is self._devices_tick:
            return
        self._devices_tick = controller
        self.device_restarts += 1
        for device in self._restartable:
            if device.name in self.device_problems:
                continue
            try:
                device.restart()
            except Exception as exc:  # noqa: BLE001 - a device's failure must not stop the loop
                self.device_problems[device.name] = first_line(exc)
                self.session.stats.note(f"{device.name} stopped: {self.device_problems[device.name]}")

    def _check_saved(self) -> None:
        recorder = self.session.recorder
        paths = recorder.paths if recorder is not None else []
        if len(paths) > self._saved_seen:
            new = list(paths[self._saved_seen:])
            self._saved_seen = len(paths)
            if self.on_saved is not None:
                self.on_saved(new)

    def _snapshot(self) -> Snapshot:
        s = self.session
        c = s.controller  # the tick's state; a reset replaces it with the next scene's
        if c.model is not self._model:
            self._model = c.model
            self._generation += 1
        data = c.data
        recorder = s.recorder
        return Snapshot(
            tick=self._ticks,
            generation=self._generation,
            model=c.model,
            seed=s.seed,
            sim_time=float(data.time),
            qpos=data.qpos.copy(),
            mocap_pos=data.mocap_pos.copy(),
            mocap_quat=data.mocap_quat.copy(),
            xpos=data.xpos.copy(),  # the tick ran mj_kinematics: current
            xquat=data.xquat.copy(),
            targets=tuple(c.target_pose(i) for i in range(c.n_arms)),
            ee=tuple(c.ee_pose(i) for i in range(c.n_arms)),
            tracking_error_m=(c.tracking_errors[-1].copy() if c.tracking_errors else np.zeros(c.n_arms)),
            gripper_open=tuple(a.gripper_open for a in c.arms),
            success=bool(c.success()),
            recording=recorder is not None and recorder.recording,
            recording_error=recorder.error if recorder is not None else None,
            episode_steps=recorder.steps if recorder is not None else 0,
            episodes_saved=recorder.episodes_saved if recorder is not None else 0,
            episodes_discarded=recorder.episodes_discarded if recorder is not None else 0,
            ik_failures=s.stats.ik_failures,
            input_time=self._input_time,
        )
