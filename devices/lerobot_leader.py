"""LeRobot leader arms (SO-100, SO-101, Koch) as input devices, through LeRobot's own teleoperator classes.

`so101_leader:PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]` (and `so100_leader`,
`koch_leader`). LeRobot and its servo SDKs are imported only when a leader starts (the `hardware`
extra). Calibration is LeRobot's: the file `lerobot-calibrate` wrote, found where LeRobot looks
(or in `calibration=DIR`); the leader is connected with `connect(calibrate=False)` and checked here,
because LeRobot's own `calibrate()` waits on stdin.

Two ways to drive, chosen against the session's robot before the first tick:
  joints   the map's robot (the so101 for the repository's maps): the leader's joints, through the
           joint map (devices/joint_map.py), are the arm's joint targets, applied without IK.
  retarget any other robot, SO-10x leaders only: the leader's gripper pose through the so101's
           kinematics (devices/retarget.py); its change since engagement, the position times
           `scale` (default: the robots' reach ratio), moves the robot's EE target.
The leader's gripper gives the robot's gripper opening (0 closed .. 1 open) either way.

Engaging without a jump (GELLO's rule): at the start of an episode, and when the leader comes
back after an unplug, an arm more than 0.5 rad (a joint) or 5 cm / 0.5 rad (the EE) from where
the leader says eases toward it, at most 0.05 rad or 1 cm (and 0.05 rad of turn) a control
tick; status() says "easing in" until it has caught up. A reader thread of its own polls the bus
(`get_action()`), so a slow or unplugged bus never stalls the control tick; unplugged, the device
says "disconnected", sends nothing (the arm holds its last target) and tries to reopen the port
every second. Retargeting keeps the episode's origin across an unplug, so a leader moved while
unplugged brings the arm to where it says, eased in, rather than shifting the origin.
"""

from __future__ import annotations

import math
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

from devices.base import DeviceError
from devices.command import Command
from devices.joint_map import JointMap, JointMapError, builtin_map_path, load_joint_map
from devices.retarget import LEADER_ROBOT, LeaderKinematics, Retarget, quat_angle, slerp_toward, to_base, to_world
from devices.serial_ports import port_problem
from devices.view import SessionView

LEADER_TYPES = ("so101_leader", "so100_leader", "koch_leader")
MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")  # LeRobot's names, ids 1-6
UNITS = {"so101_leader": "degrees", "so100_leader": "degrees", "koch_leader": "range"}  # LeRobot's normalisation
OPTION_KEYS = ("id", "calibration", "map", "scale", "arm")
SPEC_HELP = "PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]"

ENGAGE_JOINT_RAD = 0.5  # a joint further than this from the leader: ease in
EASE_JOINT_RAD = 0.05  # per control tick
ENGAGE_POS_M = 0.05  # retargeting: an EE target further than this (or ENGAGE_TURN_RAD) from the leader's: ease in
ENGAGE_TURN_RAD = 0.5
EASE_POS_M = 0.01  # per control tick
EASE_TURN_RAD = 0.05  # per control tick
READ_PERIOD_S = 0.005  # the reader thread's pause between bus reads (a sync read takes about 0.5-3 ms)
RECONNECT_S = 1.0  # between tries to reopen an unplugged leader
LOST_AFTER_FAILURES = 2  # failed reads in a row (LeRobot retries each twice) that mean the leader is gone, not a glitch
CONNECT_TRIES = 3  # a bus that times out while connecting (a busy machine, a glitch) is tried again this often
INSTALL_HINT = "pip install 'mujoco-teleop[hardware]' (LeRobot with its Feetech and Dynamixel SDKs)"


class LeaderError(DeviceError):
    """A leader arm that cannot be used: it stops the command (one line, exit 2) rather than being skipped."""


@runtime_checkable
class _Notes(Protocol):
    """A view that keeps operator notes (the session's controller: the page and `teleop run` show them)."""

    def note(self, message: str) -> None: ...


@dataclass(frozen=True)
class LeaderSpec:
    """What a `--device` word asks for (values keep their case)."""

    kind: str  # one of LEADER_TYPES
    port: str
    id: str | None = None
    calibration: Path | None = None
    map: Path | None = None
    scale: float | None = None
    arm: int = 0


def parse_leader_spec(kind: str, arg: str, n_arms: int = 1) -> LeaderSpec:
    """Parse "PORT[:key=value...]" of a leader word; PORT is everything before the first `key=value` token.

    PORT and the values may themselves hold ':' (/dev/serial/by-path names do): a token that is not
    `key=value` joins the part before it; a `key=value` with an unknown key is an error.
    """
    word = f"{kind}:{arg}"
    port_parts: list[str] = []
    options: dict[str, list[str]] = {}
    current: list[str] = port_parts
    for token in arg.split(":"):
        key, eq, value = token.partition("=")
        if eq and key.strip().lower() in OPTION_KEYS:
            key = key.strip().lower()
            if key in options:
                raise LeaderError(f"{word}: option {key}= given twice")
            current = options[key] = [value]
        elif eq and key.strip().isidentifier():
            raise LeaderError(f"{word}: unknown option {key.strip()!r} (use {SPEC_HELP})")
        else:
            current.append(token)
    port = ":".join(port_parts).strip()
    if not port:
        raise LeaderError(f"{kind} needs its serial port: {kind}:{SPEC_HELP} (e.g. {kind}:/dev/ttyACM0)")
    values = {k: ":".join(v).strip() for k, v in options.items()}
    for key, value in values.items():
        if not value:
            raise LeaderError(f"{word}: option {key}= needs a value")
    scale = None
    if "scale" in values:
        try:
            scale = float(values["scale"])
        except ValueError:
            scale = math.nan
        if not (math.isfinite(scale) and scale > 0):
            raise LeaderError(f"{word}: scale= must be a positive number (got {values['scale']!r})")
    arm = 0
    if "arm" in values:
        n = max(int(n_arms), 1)
        if not values["arm"].isdigit() or int(values["arm"]) >= n:
            raise LeaderError(f"{word}: arm={values['arm']} but the robot has {n} arm(s) (use arm=0..{n - 1})")
        arm = int(values["arm"])
    return LeaderSpec(
        kind=kind, port=port, id=values.get("id"),
        calibration=Path(values["calibration"]).expanduser() if "calibration" in values else None,
        map=Path(values["map"]).expanduser() if "map" in values else None, scale=scale, arm=arm,
    )


def calibrate_command(spec: LeaderSpec) -> str:
    """The `lerobot-calibrate` command that writes the calibration this leader looks for."""
    parts = [f"lerobot-calibrate --teleop.type={spec.kind} --teleop.port={spec.port}"]
    if spec.id is not None:
        parts.append(f"--teleop.id={spec.id}")
    if spec.calibration is not None:
        parts.append(f"--teleop.calibration_dir={spec.calibration}")
    return " ".join(parts)


def _stderr(message: str) -> None:
    print(message, file=sys.stderr, flush=True)


def _lerobot_teleoperator(spec: LeaderSpec):
    """LeRobot's teleoperator object for the spec (not connected); LeaderError when LeRobot is missing."""
    try:
        if spec.kind == "koch_leader":
            from lerobot.teleoperators.koch_leader import KochLeader, KochLeaderConfig

            config = KochLeaderConfig(port=spec.port, id=spec.id, calibration_dir=spec.calibration)
            make = KochLeader
        else:
            from lerobot.teleoperators.so_leader import SOLeader, SOLeaderTeleopConfig

            config = SOLeaderTeleopConfig(port=spec.port, id=spec.id, calibration_dir=spec.calibration, use_degrees=True)
            make = SOLeader
    except ImportError as exc:
        raise LeaderError(f"{spec.kind} needs LeRobot's hardware support ({exc.name or exc} is missing): {INSTALL_HINT}") from None
    try:
        return make(config)
    except Exception as exc:  # noqa: BLE001 - a calibration file LeRobot cannot parse: draccus raises many kinds
        raise LeaderError(
            f"{spec.kind}:{spec.port}: cannot read the calibration file ({type(exc).__name__}: {first_words(exc)}); "
            f"calibrate again: {calibrate_command(spec)}"
        ) from None


def _motor_problem(bus, spec: LeaderSpec) -> tuple[str, bool]:
    """What LeRobot's motor check found, in one line (servos that did not answer, or of the wrong model), and
    whether trying again cannot help (a wrong model)."""
    missing, wrong = [], []
    for name, motor in bus.motors.items():
        expected = bus.model_number_table[motor.model]
        try:
            found = bus.ping(name)
        except Exception:  # noqa: BLE001 - a failing ping is a missing servo
            found = None
        if found is None:
            missing.append(f"{motor.id} ({name})")
        elif found != expected:
            wrong.append(f"{motor.id} ({name}) is model {found}, expected {motor.model} ({expected})")
    where = f"{spec.kind}:{spec.port}"
    if wrong:
        return f"{where}: wrong servo model: servo {'; '.join(wrong)}: is this a {spec.kind}?", True
    if len(missing) == len(bus.motors):
        return (f"{where}: no servo answered (ids 1-{len(bus.motors)} expected): is the arm powered, on this port, "
                f"and a {spec.kind}?"), False
    if missing:
        return f"{where}: servos {', '.join(missing)} did not answer: check their cables", False
    return f"{where}: the servos' check failed", False


def connect_leader(spec: LeaderSpec, tries: int = CONNECT_TRIES):
    """LeRobot's teleoperator for the spec, connected without calibrating and checked; LeaderError otherwise.

    A failure to talk to the servos is tried again (`tries` in all): a status packet that came late
    on a busy machine must not stop the command; a missing port or calibration is not.
    """
    problem = port_problem(spec.port, "the leader")
    if problem:
        raise LeaderError(f"{spec.kind}: {problem}")
    if spec.calibration is not None and not spec.calibration.is_dir():
        raise LeaderError(f"{spec.kind}:{spec.port}: calibration={spec.calibration} is not a folder; {calibrate_command(spec)} writes one")
    for attempt in range(tries):
        try:
            return _connect_once(spec)
        except _BusTrouble as exc:
            if attempt >= tries - 1:
                raise LeaderError(str(exc)) from None
            time.sleep(0.1)
    raise AssertionError("unreachable")


class _BusTrouble(Exception):
    """The servos did not answer as they should while connecting: worth another try."""


def _connect_once(spec: LeaderSpec):
    leader = _lerobot_teleoperator(spec)
    where = f"{spec.kind}:{spec.port}"
    try:
        leader.connect(calibrate=False)
    except RuntimeError as exc:  # LeRobot's motor check: a servo missing or of the wrong model
        problem, lasting = _motor_problem(leader.bus, spec) if leader.bus.is_connected else (f"{where}: {first_words(exc)}", False)
        _drop(leader)
        raise (LeaderError if lasting else _BusTrouble)(problem) from None
    except (ConnectionError, OSError) as exc:
        _drop(leader)
        cause = exc.__cause__ or exc
        if isinstance(cause, PermissionError):
            raise LeaderError(f"{spec.kind}: {port_problem(spec.port, 'the leader') or f'permission denied on {spec.port}'}") from None
        raise _BusTrouble(f"{where}: cannot talk to the servos ({first_words(cause)})") from None
    try:
        calibrated = leader.is_calibrated
    except Exception as exc:  # noqa: BLE001 - a read failing mid-check: the bus went away
        _drop(leader)
        raise _BusTrouble(f"{where}: cannot read the servos' calibration ({first_words(exc)})") from None
    if not calibrated:
        path = leader.calibration_fpath
        _drop(leader)
        if not Path(path).is_file():
            raise LeaderError(f"{where}: no calibration file {path}; calibrate the leader: {calibrate_command(spec)}")
        raise LeaderError(f"{where}: the calibration in {path} does not match the servos; calibrate again: {calibrate_command(spec)}")
    return leader


def first_words(exc: BaseException) -> str:
    """An exception's first line, or its type's name."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _drop(leader) -> None:
    """Close LeRobot's port without another word to the servos (they may be gone)."""
    try:
        if leader.bus.is_connected:
            leader.bus.disconnect(disable_torque=False)
    except Exception:  # noqa: BLE001 - closing a port that went away
        pass


def _reading(action: dict) -> dict[str, float]:
    """LeRobot's {"shoulder_pan.pos": value} as {"shoulder_pan": value}."""
    return {k.removesuffix(".pos"): float(v) for k, v in action.items()}


class LeaderArm:
    """One LeRobot leader arm driving one arm of the session (see the module docstring)."""

    def __init__(self, spec: LeaderSpec, log: Callable[[str], None] | None = None) -> None:
        if spec.kind not in LEADER_TYPES:
            raise LeaderError(f"unknown leader type {spec.kind!r} (known: {', '.join(LEADER_TYPES)})")
        self.spec = spec
        self.kind = spec.kind
        self.arm = spec.arm
        self.name = f"{spec.kind}:{spec.port}" + (f":arm={spec.arm}" if spec.arm else "")
        self.log = log or _stderr
        self.problem = ""  # why the leader is disconnected, for the panel
        self.readings = 0  # bus reads since start
        self.reconnects = 0
        try:
            self.map = load_joint_map(spec.map or builtin_map_path(spec.kind))
        except JointMapError as exc:
            raise LeaderError(str(exc)) from None
        self._check_map(self.map)
        self._leader = None
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected = False
        self._sample: dict[str, float] | None = None
        self._engage = True  # (re)engage at the next poll: an episode began or the leader came back
        self._new_episode = True  # the next engagement starts a new retargeting origin
        self._easing = False
        self._last_time = -math.inf
        self._announced = ""
        self._notes: list[str] = []
        # chosen by check(): "joints" or "retarget"
        self.mode: str | None = None
        self._index: list[int | None] = []  # arm joint -> index of the map rule that drives it
        self._out_q: np.ndarray | None = None
        self._out_pose: tuple[np.ndarray, np.ndarray] | None = None
        self._kin: LeaderKinematics | None = None
        self._retarget: Retarget | None = None

    def _check_map(self, jmap: JointMap) -> None:
        where = f"{self.spec.kind}: map {jmap.path}"
        if jmap.units != UNITS[self.spec.kind]:
            raise LeaderError(f"{where}: units = {jmap.units!r}, but LeRobot reads a {self.spec.kind} in {UNITS[self.spec.kind]!r}")
        unknown = [j for j in jmap.leader_joints if j not in MOTORS]
        if unknown:
            raise LeaderError(f"{where}: no leader joint {unknown[0]!r} on a {self.spec.kind} (it has {', '.join(MOTORS)})")

    # -- life cycle -------------------------------------------------------
    def start(self) -> None:
        """Connect and check now (a wrong setup is one line before anything runs), then read in the background."""
        self._leader = connect_leader(self.spec)
        try:
            self._sample = _reading(self._leader.get_action())
        except Exception as exc:  # noqa: BLE001 - the first read: any failure means the leader is unusable
            _drop(self._leader)
            self._leader = None
            raise LeaderError(f"{self.name}: the servos do not answer reads ({first_words(exc)})") from None
        self.readings = 1
        self._connected = True  # said at the first tick, as "connected" or "easing in"
        self._thread = threading.Thread(target=self._run, name=f"{self.name}-reader", daemon=True)
        self._thread.start()

    def restart(self) -> None:
        """A new episode: engage again (with the ease-in if the arm is far from the leader)."""
        with self._lock:
            self._engage = self._new_episode = True
            self._easing = False

    def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=3.0)
        leader, self._leader = self._leader, None
        if leader is not None:
            try:
                leader.disconnect()
            except Exception:  # noqa: BLE001 - closing a leader that went away
                _drop(leader)
        self._connected = False

    @property
    def finished(self) -> bool:
        return False

    def status(self) -> str:
        if self._stop.is_set():
            return "closed"
        if not self._connected:
            return "disconnected"
        return "easing in" if self._easing else "connected"

    # -- reading thread ---------------------------------------------------
    def _run(self) -> None:
        failures = 0  # failed reads in a row
        while not self._stop.is_set():
            leader = self._leader
            if leader is None:
                if self._stop.wait(RECONNECT_S):
                    break
                self._reopen()
                continue
            try:
                sample = _reading(leader.get_action())
            except Exception as exc:  # noqa: BLE001 - unplugged: pyserial, LeRobot and the OS raise many kinds
                failures += 1
                if failures >= LOST_AFTER_FAILURES:
                    failures = 0
                    self._lost(first_words(exc))
                continue
            failures = 0
            with self._lock:
                self._sample = sample
                self.readings += 1
            self._stop.wait(READ_PERIOD_S)

    def _reopen(self) -> None:
        try:
            leader = connect_leader(self.spec, tries=1)  # the next try is RECONNECT_S away
            sample = _reading(leader.get_action())
        except Exception as exc:  # noqa: BLE001 - still unplugged (or not answering yet): try again later
            self.problem = first_words(exc)
            return
        with self._lock:
            self._leader = leader
            self._sample = sample
            self._connected = True
            self._engage = True
            self.problem = ""
            self.reconnects += 1
        self._announce("connected")

    def _lost(self, why: str) -> None:
        leader, self._leader = self._leader, None
        if leader is not None:
            _drop(leader)
        with self._lock:
            self._connected = False
            self._easing = False
            self.problem = why
        self._announce("disconnected")

    def _announce(self, status: str) -> None:
        """Say a status change once, on the terminal now and as a session note at the next poll."""
        why = " (the servos stopped answering: unplugged? trying again every second; the arm holds)" if status == "disconnected" else ""
        line = f"{self.name}: {status}{why}"
        with self._lock:
            if status == self._announced:
                return
            self._announced = status
            self._notes.append(line)
        self.log(line)

    # -- control tick -----------------------------------------------------
    def check(self, view: SessionView) -> None:
        """Choose joints or retargeting for the session's robot; LeaderError when neither fits."""
        if not 0 <= self.arm < view.n_arms:
            raise LeaderError(f"{self.name}: arm={self.arm} but the robot has {view.n_arms} arm(s)")
        robot = view.robot_name
        if robot == self.map.robot:
            names = view.joint_names(self.arm)
            by_robot = {r.robot: i for i, r in enumerate(self.map.joints)}
            missing = [r.robot for r in self.map.joints if r.robot not in names]
            if missing:
                raise LeaderError(f"{self.name}: map {self.map.path} names joint {missing[0]!r}, which {robot} lacks "
                                  f"(its joints: {', '.join(names)})")
            self._index = [by_robot.get(n) for n in names]
            self.mode = "joints"
            return
        if self.spec.kind == "koch_leader" or self.map.robot != LEADER_ROBOT:
            raise LeaderError(
                f"{self.name} drives the {self.map.robot} joint for joint only (no {self.spec.kind.removesuffix('_leader')} "
                f"model here to retarget from): use --robot {self.map.robot}, or an SO-100/SO-101 leader for {robot}"
            )
        self._kin = self._kin or LeaderKinematics()  # the so101 model, compiled once
        scale = self.spec.scale if self.spec.scale is not None else view.reach / self._kin.reach
        self._retarget = Retarget(scale)
        self.mode = "retarget"

    def poll(self, view: SessionView, dt: float) -> list[Command]:
        """The newest leader reading as this tick's commands (nothing while disconnected: the arm holds)."""
        if self.mode is None:
            self.check(view)
        with self._lock:
            sample = self._sample
            connected = self._connected
            engage, self._engage = self._engage, False
            new_episode, self._new_episode = self._new_episode, False
        now = view.time
        if now < self._last_time:  # the session was reset (a new episode that nobody announced)
            engage = new_episode = True
        self._last_time = now
        if not connected or sample is None:
            if engage:  # keep the request for when the leader is back
                with self._lock:
                    self._engage = True
                    self._new_episode = self._new_episode or new_episode
            self._flush_notes(view)
            return []
        gripper = self.map.gripper_opening(sample)
        if self.mode == "joints":
            commands = self._joints(view, sample, engage, gripper)
        else:
            commands = self._pose(view, sample, engage, new_episode, gripper)
        self._announce("easing in" if self._easing else "connected")
        self._flush_notes(view)
        return commands

    def _flush_notes(self, view: SessionView) -> None:
        """Hand the status lines said since the last tick to the session's notes (on the control thread)."""
        with self._lock:
            notes, self._notes = self._notes, []
        if isinstance(view, _Notes):
            for line in notes:
                view.note(line)

    def _joints(self, view: SessionView, sample: dict[str, float], engage: bool, gripper: float | None) -> list[Command]:
        """Position mode: the map's joint angles, eased in at most EASE_JOINT_RAD a tick after engaging."""
        if engage or self._out_q is None:
            self._out_q = view.joint_targets(self.arm).astype(float)
        lo, hi = view.joint_limits(self.arm)
        values = self.map.robot_joints(sample)
        rules = self.map.joints
        want = np.array([self._out_q[i] if k is None else values[rules[k].robot] for i, k in enumerate(self._index)])
        want = np.minimum(np.maximum(want, lo), hi)
        if engage:
            self._easing = bool(np.max(np.abs(want - view.joint_positions(self.arm)), initial=0.0) > ENGAGE_JOINT_RAD)
        if self._easing:
            step = np.clip(want - self._out_q, -EASE_JOINT_RAD, EASE_JOINT_RAD)
            self._out_q = self._out_q + step
            if np.max(np.abs(want - self._out_q), initial=0.0) <= 1e-9:
                self._out_q, self._easing = want, False
        else:
            self._out_q = want
        return [Command(joints=self._out_q.copy(), gripper_opening=gripper, arm=self.arm, source=self.name)]

    def _pose(self, view: SessionView, sample: dict[str, float], engage: bool, new_episode: bool,
              gripper: float | None) -> list[Command]:
        """Retargeting: the leader's gripper motion since engagement moves the EE target, eased at most 1 cm a tick."""
        assert self._kin is not None and self._retarget is not None
        leader = self._kin.pose(self.map.robot_joints(sample))
        base_pos, base_quat = view.base_pose(self.arm)
        if new_episode or not self._retarget.engaged:
            self._retarget.engage(leader, to_base(base_pos, base_quat, *view.target_pose(self.arm)))
        pos, quat = to_world(base_pos, base_quat, *self._retarget.target(leader))
        if engage or self._out_pose is None:
            here = view.target_pose(self.arm)
            self._out_pose = (here[0].astype(float), here[1].astype(float))
            far = np.linalg.norm(pos - self._out_pose[0]) > ENGAGE_POS_M or quat_angle(quat, self._out_pose[1]) > ENGAGE_TURN_RAD
            self._easing = bool(far)
        if self._easing:
            cur_pos, cur_quat = self._out_pose
            gap = pos - cur_pos
            dist = float(np.linalg.norm(gap))
            turned = quat_angle(cur_quat, quat) <= EASE_TURN_RAD  # slerp_toward reaches it this tick
            new_pos = pos.copy() if dist <= EASE_POS_M else cur_pos + gap * (EASE_POS_M / dist)
            self._out_pose = (new_pos, slerp_toward(cur_quat, quat, EASE_TURN_RAD))
            if dist <= EASE_POS_M and turned:
                self._easing = False
        else:
            self._out_pose = (pos, quat)
        commands = [Command(target_pos=self._out_pose[0].copy(), target_quat=self._out_pose[1].copy(), arm=self.arm, source=self.name)]
        if gripper is not None:
            commands.append(Command(gripper_opening=gripper, arm=self.arm, source=self.name))
        return commands

    def reading(self) -> dict[str, float] | None:
        """The newest leader reading (LeRobot's units: degrees or -100..100, gripper 0..100), for panels."""
        with self._lock:
            return None if self._sample is None else dict(self._sample)


def make_leader(kind: str, arg: str, n_arms: int = 1, log: Callable[[str], None] | None = None) -> LeaderArm:
    """A leader device from its spec word's parts (not started); LeaderError for a bad option or map."""
    return LeaderArm(parse_leader_spec(kind, arg, n_arms), log=log)
