"""A real follower arm that mirrors the simulated one (issue 47): LeRobot's `SOFollower`, fed by a thread of its own.

`--follower so101_follower:PORT[:id=NAME][:calibration=DIR][:map=FILE][:max_step=DEG]` pairs a real SO-101 with
the simulated so101. It connects the way a leader does (devices/lerobot_connect.py: pings, the calibration, then
LeRobot's connect, patiently). A thread of its own, at the control rate, reads the simulated arm's joint targets
(the arm actuators' ctrl, radians, and the gripper's ctrl), turns them into LeRobot's degrees (and the gripper's
0..100) through a leader's joint map inverted (its `map=`, the driving leader's `map=`, else the built-in one:
teleop/control/follower_spec.py), clamps each joint to the follower's calibrated range (counted) and its
change to `max_step` degrees a tick (the gripper's to max_step of its 0..100, as LeRobot does; `max_step` is also
LeRobot's own `max_relative_target`, measured from the servo's present position), and sends it with
`send_action`. So a follower that starts elsewhere eases to the simulated pose ("catching up") before
it tracks it ("tracking"), and a reset to the next seed is followed at `max_step`, never as a jump; the
control tick itself never waits on the serial bus. Torque goes off on every way out (issue 56 item 2): a
fault, Ctrl-C or SIGTERM anywhere in `open()` (before and after LeRobot's connect enabled it) releases the arm
before the error goes on; every bus operation of the thread (a send, a reconnect inside LeRobot's connect)
holds one lock and starts only if the follower is not closing, so `close()` waits for the one in flight, then
disables torque, and nothing is sent after. LeRobot is imported only when a follower is opened.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from devices.base import DeviceError
from devices.lerobot_connect import ArmError, ArmWords, connect_arm, patiently, release
from devices.serial_ports import port_problem
from scenes.errors import first_line
from scenes.workers.interrupts import shielded
from teleop.control.follower_spec import FollowerSpec, MotorMap, check_pairing, leader_map_of, motor_map, parse_follower_spec

if TYPE_CHECKING:  # annotations only
    from teleop.control.session import Session

TRACKING_GAP_DEG = 3.0  # tracking: nothing held back by the step limit, every arm joint this close (or max_step)
RECONNECT_S = 1.0  # between tries to reach a follower that stopped answering
STALL_S = 0.5  # failed sends for this long, none answered, and the follower is "disconnected"; a busy host or
# USB adapter drops a reply now and then (counted in `errors`), which is not a pulled cable
_CLAMP_WARNING = "Relative goal position magnitude had to be clamped"  # LeRobot logs this on every clamped send


class _DropClampWarnings(logging.Filter):
    """LeRobot warns on the root logger at every clamped send; easing in clamps every tick: counted instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_CLAMP_WARNING)


class Follower:
    """One real follower arm, connected, that mirrors a session's simulated arm once `follow` starts it.

    `open()` connects (every fault one line, DeviceError, before anything is sent); `follow(session)`
    starts the sending thread; `status()` is what the page and the status file show; `close()` stops
    sending and disables torque, and may be called any number of times.
    """

    def __init__(self, spec: FollowerSpec, rate_hz: float = 30.0, arm: int = 0) -> None:
        self.spec = spec
        self.rate_hz = float(rate_hz)
        self.arm = arm
        self.robot: Any = None  # lerobot SOFollower once opened
        self.map: MotorMap | None = None
        self.state = "disconnected"
        self.sent = 0  # actions sent
        self.clamped = 0  # goals pulled into the follower's calibrated range
        self.errors = 0  # sends that failed (a follower that stopped answering)
        self.max_gap_deg: float | None = None  # largest |present - target| over the arm joints, degrees
        self.error: str | None = None  # the last failure, one line
        self._lo = self._hi = np.zeros(0)  # the motors' calibrated range in LeRobot's units
        self._last: np.ndarray | None = None  # the goals sent last (LeRobot's units), where the next may step from
        self._stop = threading.Event()
        self._bus_lock = threading.Lock()  # held by every bus operation of the thread, and by close()
        self._thread: threading.Thread | None = None
        self._session: Session | None = None
        self._send_times: list[float] = []
        self._filter = _DropClampWarnings()
        self._closed = False

    # -- connecting ------------------------------------------------------------------------------------
    def words(self) -> ArmWords:
        """How the connect's messages name this follower."""
        return ArmWords(where=self.spec.port, what="the follower", model_of="an SO-101 follower",
                        calibrate=self.spec.calibrate_hint())

    def open(self, joint_names: tuple[str, ...], leader_map: Path | None = None) -> None:
        """Connect to the arm, checked (devices/lerobot_connect.py): its port, the servos answering with the right
        model, the calibration, then LeRobot's connect (torque on) and a first read of where it stands.

        `leader_map`: the `map=` of the leader driving the session, used when the follower has none of its own.
        Any way out but a normal return (a fault, Ctrl-C, SIGTERM) leaves the arm with torque off and its port closed.
        """
        spec = self.spec
        self.map = motor_map(spec, joint_names, leader_map)
        problem = port_problem(spec.port, "the follower")
        if problem is not None:
            raise DeviceError(problem)
        if spec.calibration is not None and not spec.calibration.is_dir():
            raise DeviceError(f"{spec.calibration}: no such calibration directory")
        from lerobot.robots.so_follower import SOFollower, SOFollowerRobotConfig

        config = SOFollowerRobotConfig(port=spec.port, id=spec.id, calibration_dir=spec.calibration,
                                       max_relative_target=float(spec.max_step_deg), cameras={}, use_degrees=True)
        robot = SOFollower(config)
        unknown = [m for m in self.map.motors if m not in robot.bus.motors]
        if unknown:
            raise DeviceError(f"{self.map.source}: {unknown[0]!r} is not a motor of the {spec.kind}")
        connected = False  # LeRobot's connect returned: torque is on, and this method must turn it off on the way out
        try:
            try:
                connect_arm(robot, self.words(), energises=True)  # released by itself on any way out of it
                connected = True
            except ArmError as exc:
                raise DeviceError(str(exc)) from None
            self.robot = robot
            logging.getLogger().addFilter(self._filter)
            self._lo, self._hi = self._ranges(robot)
            try:
                self._last = patiently(self._present)
            except Exception as exc:  # noqa: BLE001
                raise DeviceError(f"{spec.port}: the follower stopped answering ({first_line(exc)})") from None
            self.state = "connected"
        except BaseException:  # a fault, Ctrl-C or SIGTERM after LeRobot's connect enabled torque
            if connected:
                self.robot = robot
                _, interrupted = shielded(self.close)
                if interrupted:
                    raise KeyboardInterrupt from None
            raise

    def _ranges(self, robot: Any) -> tuple[np.ndarray, np.ndarray]:
        """The map's motors' calibrated ranges in LeRobot's units (degrees about the range's middle; gripper 0..100)."""
        cal = robot.bus.calibration
        lo, hi = [], []
        for motor in self.map.motors:
            c = cal[motor]
            if robot.bus.motors[motor].norm_mode.value == "degrees":
                steps = robot.bus.model_resolution_table[robot.bus.motors[motor].model] - 1
                mid = (c.range_min + c.range_max) / 2
                lo.append((c.range_min - mid) * 360.0 / steps)
                hi.append((c.range_max - mid) * 360.0 / steps)
            else:  # the gripper: 0..100 over its calibrated range
                lo.append(0.0)
                hi.append(100.0)
        return np.array(lo), np.array(hi)

    # -- following -------------------------------------------------------------------------------------
    def follow(self, session: Session) -> None:
        """Start sending `session`'s simulated arm targets at the control rate (its own thread)."""
        if self.robot is None:
            raise RuntimeError("open() the follower first")
        self._session = session
        self.rate_hz = session.control_hz
        self._thread = threading.Thread(target=self._run, name="teleop-follower", daemon=True)
        self._thread.start()

    def targets(self) -> np.ndarray | None:
        """LeRobot's numbers for the simulated arm's joint targets now (None before the scene's first tick)."""
        session = self._session
        if session is None:
            return None
        c = session.controller  # a reset replaces it: read once
        if c.steps == 0 and c.data.time == 0.0:
            return None  # a new scene whose ctrl is not written yet
        arm = c.arms[self.arm]
        ctrl = c.data.ctrl
        q = ctrl[arm.ctrl_ids]
        opening = None
        if arm.gripper_id is not None:
            g = arm.ik.arm.gripper
            opening = (float(ctrl[arm.gripper_id]) - g.closed) / (g.open - g.closed)
        return np.array(self.map.values(q, opening))

    def _present(self) -> np.ndarray:
        present = self.robot.bus.sync_read("Present_Position", list(self.map.motors), num_retry=2)
        return np.array([float(present[m]) for m in self.map.motors])

    def _run(self) -> None:
        period = 1.0 / self.rate_hz
        due = time.perf_counter()
        retry_at = 0.0
        failing_since: float | None = None  # when the sends began to fail (perf_counter), None while they succeed
        while not self._stop.is_set():
            due += period
            now = time.perf_counter()
            if due < now - 1.0:
                due = now  # a stall over a second: start the schedule again
            note = None
            with self._bus_lock:  # close() holds it while it disables torque: nothing is sent after
                if self._stop.is_set():
                    break
                if self.state == "disconnected":
                    if now >= retry_at:
                        retry_at = now + RECONNECT_S
                        self._reconnect()
                else:
                    try:
                        self.send_once()
                        failing_since = None
                    except Exception as exc:  # noqa: BLE001 - a follower that stops answering is shown, then retried
                        self.errors += 1
                        self.error = first_line(exc)
                        failing_since = now if failing_since is None else failing_since
                        if time.perf_counter() - failing_since >= STALL_S:
                            self.state = "disconnected"
                            failing_since = None
                            retry_at = time.perf_counter() + RECONNECT_S
                            note = f"follower {self.spec.port} stopped answering: {self.error}"
            if note is not None and self._session is not None:
                self._session.stats.note(note)
            self._stop.wait(max(0.0, due - time.perf_counter()))

    def send_once(self) -> None:
        """One send: the newest targets, clamped to the calibrated range and to max_step from the last goal."""
        wanted = self.targets()
        if wanted is None or self._last is None:
            return
        inside = np.minimum(np.maximum(wanted, self._lo), self._hi)
        if inside.tolist() != wanted.tolist():
            self.clamped += 1
        step = self.spec.max_step_deg
        goal = np.minimum(np.maximum(inside, self._last - step), self._last + step)
        motors = self.map.motors
        sent = self.robot.send_action({f"{m}.pos": float(v) for m, v in zip(motors, goal)})
        out = np.array([float(sent[f"{m}.pos"]) for m in motors])
        self._last = out
        self.sent += 1
        stamp = time.monotonic()
        self._send_times.append(stamp)
        if len(self._send_times) > 60:
            del self._send_times[:-60]
        present = self._present()
        n = len(self.map.joints)
        self.max_gap_deg = float(np.max(np.abs(present[:n] - inside[:n]))) if n else 0.0
        eased = bool(np.any(np.abs(out - inside) > 1e-6))  # the step limit (ours or LeRobot's) held a joint back
        self.state = "catching up" if eased or self.max_gap_deg > max(TRACKING_GAP_DEG, step) else "tracking"

    def _reconnect(self) -> None:
        """Try to reach a follower that stopped answering (the bus lock held); from its present pose it eases in again."""
        robot = self.robot
        try:
            if not robot.bus.is_connected:  # the port failed: the whole connect again, checked, one quick try
                connect_arm(robot, self.words(), energises=True, patient=False)
            else:
                robot.bus.enable_torque(num_retry=1)  # a servo that lost power comes back with torque off
            self._last = self._present()
        except Exception as exc:  # noqa: BLE001 - still away: try again later
            self.error = first_line(exc)
            if robot.bus.is_connected and not isinstance(exc, (ConnectionError, RuntimeError)):
                release(robot, torque_off=True)  # the port itself failed: torque off as far as it goes, reopen next time
            return
        self.state = "catching up"

    # -- what the page shows -------------------------------------------------------------------------------
    def hz(self) -> float:
        """Sends per second over the last ones kept (0 before two)."""
        times = self._send_times[-31:]
        if len(times) < 2 or time.monotonic() - times[-1] > 1.0:
            return 0.0
        return (len(times) - 1) / (times[-1] - times[0]) if times[-1] > times[0] else 0.0

    def status(self) -> dict:
        """{"state", "max_gap_deg", "clamped", "sent", "hz"} and where the follower is."""
        gap = self.max_gap_deg
        return {
            "state": self.state,
            "max_gap_deg": None if gap is None else round(gap, 2),
            "clamped": self.clamped,
            "sent": self.sent,
            "hz": round(self.hz(), 1),
            "port": self.spec.port,
            "type": self.spec.kind,
            "max_step_deg": self.spec.max_step_deg,
            "errors": self.errors,
            "error": self.error,
        }

    def line(self) -> str:
        """The panel's line: "follower: tracking, gap 1.2 deg"."""
        gap = "" if self.max_gap_deg is None else f", gap {self.max_gap_deg:.1f} deg"
        return f"follower: {self.state}{gap}"

    # -- the end ---------------------------------------------------------------------------------------------
    def close(self) -> None:
        """Stop sending, then disable torque and close the port; safe to call again, from any thread.

        The thread's bus operation in flight (a send, a reconnect inside LeRobot's connect, each bounded by
        LeRobot's timeouts) ends first; the lock then keeps it from starting another, so torque off is the
        last word the arm hears.
        """
        self._stop.set()
        with self._bus_lock:
            if self._closed:
                return
            self._closed = True
            robot, self.robot = self.robot, None
            logging.getLogger().removeFilter(self._filter)
            if robot is None:
                return
            self.state = "disconnected"
            release(robot, torque_off=True)  # every servo told, each on its own; the port closed
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)  # it only has to see the stop: no bus operation is left to it


def open_follower(text: str, session: Session, devices: str | None = None) -> Follower:
    """Parse a `--follower` value, check it mirrors this session's robot, connect, and start following.

    `devices`: the session's `--device` words; the `map=` of a leader among them driving the same arm is the
    follower's map when it has none of its own. A fault, Ctrl-C or SIGTERM before this returns: torque off.
    """
    spec = parse_follower_spec(text)
    check_pairing(spec, session.robot.name)
    follower = Follower(spec, rate_hz=session.control_hz)
    leader_map = leader_map_of(devices, follower.arm, session.controller.n_arms)
    try:
        follower.open(session.controller.joint_names(0), leader_map)
        follower.follow(session)
    except BaseException:
        _, interrupted = shielded(follower.close)
        if interrupted:
            raise KeyboardInterrupt from None
        raise
    return follower
