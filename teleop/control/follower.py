"""A real follower arm that mirrors the simulated one (issue 47): LeRobot's `SOFollower`, fed by a thread of its own.

`--follower so101_follower:PORT[:id=NAME][:calibration=DIR][:max_step=DEG]` pairs a real SO-101 with the
simulated so101. A thread of its own, at the control rate, reads the simulated arm's joint targets (the
arm actuators' ctrl, radians, and the gripper's ctrl), turns them into LeRobot's degrees (and the gripper's
0..100) through the SO-101 leader's joint map inverted (devices/leader_maps, devices/joint_map.py), clamps
each joint to the follower's calibrated range (counted) and its change to `max_step` degrees a tick (the
gripper's to max_step of its 0..100, as LeRobot does; `max_step` is also LeRobot's own `max_relative_target`,
measured from the servo's present position), and sends it with
`send_action`. So a follower that starts elsewhere eases to the simulated pose ("catching up") before
it tracks it ("tracking"), and a reset to the next seed is followed at `max_step`, never as a jump; the
control tick itself never waits on the serial bus. `close()` stops sending and disables torque (LeRobot's
`disconnect()`), whatever ended the session. LeRobot is imported only when a follower is opened. The
`--follower` value and the motor map are teleop/control/follower_spec.py.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from devices.base import DeviceError
from devices.serial_ports import DIALOUT_HINT, port_problem
from scenes.errors import first_line
from teleop.control.follower_spec import FollowerSpec, MotorMap, check_pairing, motor_map, parse_follower_spec

if TYPE_CHECKING:  # annotations only
    from teleop.control.session import Session

TRACKING_GAP_DEG = 3.0  # tracking: nothing held back by the step limit, every arm joint this close (or max_step)
RECONNECT_S = 1.0  # between tries to reach a follower that stopped answering
STALL_S = 0.5  # failed sends for this long, none answered, and the follower is "disconnected"; a busy host or
# USB adapter drops a reply now and then (counted in `errors`), which is not a pulled cable
PING_TRIES = 3  # a servo that does not answer this many pings, nor any until the bus's patience is out, is missing
PING_PATIENCE_S = 3.0  # seconds from the first ping: one waits ~35 ms for its answer, which a busy USB adapter or
# host can miss for a while; shared by the whole bus, so a port with no servo at all costs this once, not per servo
CALIBRATION_READS = 3  # reads of the servos' calibration registers that must all differ from the file to refuse it
CONNECT_TRIES = 2  # LeRobot's connect (its own handshake, then configuration writes) on a busy bus, tried at least
CONNECT_PATIENCE_S = 2.0  # this often and for this long (the servos answered our pings just before: a failure here
# is a reply that came late, which a loaded host or USB adapter makes now and then, not a missing arm)
_CLAMP_WARNING = "Relative goal position magnitude had to be clamped"  # LeRobot logs this on every clamped send


class _DropClampWarnings(logging.Filter):
    """LeRobot warns on the root logger at every clamped send; easing in clamps every tick: counted instead."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_CLAMP_WARNING)


def _patiently(read: Callable[[], Any], patience_s: float = CONNECT_PATIENCE_S) -> Any:
    """`read()`, asked again for up to `patience_s` while it raises (a reply late on a loaded host); then its error."""
    give_up = time.monotonic() + patience_s
    while True:
        try:
            return read()
        except Exception:  # noqa: BLE001 - LeRobot raises ConnectionError, the SDK IndexError on a short packet
            if time.monotonic() >= give_up:
                raise
            time.sleep(0.05)


def _ping(bus: Any, motor: str, give_up: float) -> int | None:
    """A servo's model number, or None if it answers none of PING_TRIES pings, nor any more until `give_up`
    (time.monotonic()); a garbled answer is asked again (the Feetech SDK raises IndexError on a short status packet)."""
    tries = 0
    while True:
        try:
            model = bus.ping(motor)
        except Exception:  # noqa: BLE001
            model = None
        tries += 1
        if model is not None:
            return model
        if tries >= PING_TRIES and time.monotonic() >= give_up:
            return None
        time.sleep(0.01)  # a port that fails at once is not asked in a busy loop


def _release(robot: Any) -> None:
    """Torque off and the port closed, as far as the arm still answers."""
    bus = robot.bus
    if not bus.is_connected:
        return
    try:
        bus.disconnect(disable_torque=True)
    except Exception:  # noqa: BLE001 - an arm that does not answer cannot be told; close the port anyway
        try:
            bus.port_handler.closePort()
        except Exception:  # noqa: BLE001
            pass


def _open_error(spec: FollowerSpec, exc: BaseException) -> DeviceError:
    """One line for a port LeRobot could not open (its own message is several lines)."""
    cause = exc.__cause__ or exc.__context__ or exc
    if isinstance(cause, PermissionError) or "ermission denied" in str(cause):
        return DeviceError(f"{spec.port}: {DIALOUT_HINT}")
    return DeviceError(f"{spec.port}: cannot open the follower's port ({first_line(cause) or type(cause).__name__})")


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
        self._thread: threading.Thread | None = None
        self._session: Session | None = None
        self._send_times: list[float] = []
        self._filter = _DropClampWarnings()
        self._closed = False

    # -- connecting ------------------------------------------------------------------------------------
    def open(self, joint_names: tuple[str, ...]) -> None:
        """Connect to the arm, checked: its port, the servos answering with the right model, the calibration."""
        spec = self.spec
        self.map = motor_map(spec, joint_names)
        problem = port_problem(spec.port, "the follower")
        if problem is not None:
            raise DeviceError(problem)
        if spec.calibration is not None and not spec.calibration.is_dir():
            raise DeviceError(f"{spec.calibration}: no such calibration directory")
        from lerobot.robots.so_follower import SOFollower, SOFollowerRobotConfig

        config = SOFollowerRobotConfig(port=spec.port, id=spec.id, calibration_dir=spec.calibration,
                                       max_relative_target=float(spec.max_step_deg), cameras={}, use_degrees=True)
        robot = SOFollower(config)
        if not robot.calibration_fpath.is_file():
            raise DeviceError(f"no calibration file {robot.calibration_fpath} for this follower: run `{spec.calibrate_hint()}`")
        unknown = [m for m in self.map.motors if m not in robot.bus.motors]
        if unknown:
            raise DeviceError(f"{self.map.source}: {unknown[0]!r} is not a motor of the {spec.kind}")
        self._check_bus(robot)
        give_up, attempt = time.monotonic() + CONNECT_PATIENCE_S, 0
        while True:
            attempt += 1
            try:
                robot.connect(calibrate=False)  # LeRobot's calibrate() would wait on stdin: never called
                break
            except Exception as exc:  # noqa: BLE001 - LeRobot's several lines become one
                _release(robot)  # it may have enabled torque before it failed
                if attempt >= CONNECT_TRIES and time.monotonic() >= give_up:
                    raise _open_error(spec, exc) from None
                time.sleep(0.1)
        self.robot = robot
        logging.getLogger().addFilter(self._filter)
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
        self._lo, self._hi = np.array(lo), np.array(hi)
        try:
            self._last = _patiently(self._present)
        except Exception as exc:  # noqa: BLE001
            self.close()
            raise DeviceError(f"{spec.port}: the follower stopped answering ({first_line(exc)})") from None
        self.state = "connected"

    def _check_bus(self, robot: Any) -> None:
        """Ping each servo and compare the calibration before LeRobot's connect (which would energise the arm)."""
        spec, bus = self.spec, robot.bus
        try:
            bus.connect(handshake=False)
        except Exception as exc:  # noqa: BLE001
            raise _open_error(spec, exc) from None
        try:
            give_up = time.monotonic() + PING_PATIENCE_S
            found = {name: _ping(bus, name, give_up) for name in bus.motors}
            silent = [name for name, model in found.items() if model is None]
            if len(silent) == len(found):
                raise DeviceError(f"{spec.port}: no servo answered (ids 1-6): is the follower powered and on this port?")
            if silent:
                ids = ", ".join(f"{bus.motors[n].id} ({n})" for n in silent)
                raise DeviceError(f"{spec.port}: servo {ids} did not answer: check its cable")
            for name, model in found.items():
                expected = bus.model_number_table[bus.motors[name].model]
                if model != expected:
                    raise DeviceError(f"{spec.port}: servo {bus.motors[name].id} ({name}) is model {model}, not an "
                                      f"{bus.motors[name].model.upper()} ({expected}): is this an SO-101 follower?")
            try:
                calibrated = _patiently(lambda: robot.is_calibrated)
                for _ in range(CALIBRATION_READS - 1):  # a mismatch is said only when every read finds it: a read
                    if calibrated:  # garbled on a loaded host or bus differs once, a wrong calibration every time
                        break
                    time.sleep(0.05)
                    calibrated = _patiently(lambda: robot.is_calibrated)
            except Exception as exc:  # noqa: BLE001 - it answered our pings, then stopped
                raise DeviceError(f"{spec.port}: the follower's servos stopped answering while their calibration was "
                                  f"read ({first_line(exc)})") from None
            if not calibrated:
                raise DeviceError(f"{spec.port}: the follower's servos do not match the calibration in "
                                  f"{robot.calibration_fpath}: run `{spec.calibrate_hint()}`")
        finally:
            bus.disconnect(disable_torque=False)  # nothing was enabled yet

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
                    self.error = first_line(exc) or type(exc).__name__
                    failing_since = now if failing_since is None else failing_since
                    if time.perf_counter() - failing_since >= STALL_S:
                        self.state = "disconnected"
                        failing_since = None
                        retry_at = time.perf_counter() + RECONNECT_S
                        if self._session is not None:
                            self._session.stats.note(f"follower {self.spec.port} stopped answering: {self.error}")
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
        """Try to reach a follower that stopped answering; from its present pose it eases in again."""
        robot = self.robot
        try:
            if not robot.bus.is_connected:
                robot.connect(calibrate=False)
            else:
                robot.bus.enable_torque(num_retry=1)  # a servo that lost power comes back with torque off
            self._last = self._present()
        except Exception as exc:  # noqa: BLE001 - still away: try again later
            self.error = first_line(exc) or type(exc).__name__
            if robot.bus.is_connected and not isinstance(exc, (ConnectionError, RuntimeError)):
                try:
                    robot.bus.port_handler.closePort()  # the port itself failed: reopen it next time
                except Exception:  # noqa: BLE001
                    pass
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
        """Stop sending, then disable torque and close the port (LeRobot's disconnect); safe to call again."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=5.0)
        if self._closed:
            return
        self._closed = True
        robot, self.robot = self.robot, None
        logging.getLogger().removeFilter(self._filter)
        if robot is None:
            return
        self.state = "disconnected"
        try:
            if robot.bus.is_connected:
                robot.disconnect()  # torque off on every servo (disable_torque_on_disconnect), then the port closes
        except Exception as exc:  # noqa: BLE001 - an unplugged arm cannot be told; close the port anyway
            self.error = first_line(exc) or type(exc).__name__
            try:
                robot.bus.port_handler.closePort()
            except Exception:  # noqa: BLE001
                pass


def open_follower(text: str, session: Session) -> Follower:
    """Parse a `--follower` value, check it mirrors this session's robot, connect, and start following."""
    spec = parse_follower_spec(text)
    check_pairing(spec, session.robot.name)
    follower = Follower(spec, rate_hz=session.control_hz)
    follower.open(session.controller.joint_names(0))
    follower.follow(session)
    return follower
