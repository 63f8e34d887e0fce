"""A leader arm's `--device` word and its connection through LeRobot's own teleoperator classes.

`so101_leader:PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]` (and `so100_leader`,
`koch_leader`) becomes a LeaderSpec; `connect_leader` opens it with LeRobot's `connect(calibrate=False)`
(LeRobot's own `calibrate()` waits on stdin) and checks the port, the servos and the calibration first, so
that every fault is one line (LeaderError) before anything runs. LeRobot and its servo SDKs are imported only
here, when a leader starts (the `hardware` extra). The device that reads it is devices.lerobot_leader.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from devices.base import DeviceError
from devices.serial_ports import port_problem
from scenes.numbers import number_or_nan

LEADER_TYPES = ("so101_leader", "so100_leader", "koch_leader")
MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")  # LeRobot's names, ids 1-6
UNITS = {"so101_leader": "degrees", "so100_leader": "degrees", "koch_leader": "range"}  # LeRobot's normalisation
OPTION_KEYS = ("id", "calibration", "map", "scale", "arm")
SPEC_HELP = "PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]"
CONNECT_TRIES = 3  # a bus that times out while connecting (a busy machine, a glitch) is tried again at least this often
CONNECT_PATIENCE_S = 3.0  # and for at least this long from the first try (a loaded host misses replies for a while)
INSTALL_HINT = "pip install 'mujoco-teleop[hardware]' (LeRobot with its Feetech and Dynamixel SDKs)"


class LeaderError(DeviceError):
    """A leader arm that cannot be used: it stops the command (one line, exit 2) rather than being skipped."""


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
        scale = number_or_nan(values["scale"])
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

    A failure to talk to the servos is tried again (`tries` in all, and for CONNECT_PATIENCE_S when more than one
    is allowed): a status packet that came late on a busy machine must not stop the command; a missing port or
    calibration is not.
    """
    problem = port_problem(spec.port, "the leader")
    if problem:
        raise LeaderError(f"{spec.kind}: {problem}")
    if spec.calibration is not None and not spec.calibration.is_dir():
        raise LeaderError(f"{spec.kind}:{spec.port}: calibration={spec.calibration} is not a folder; {calibrate_command(spec)} writes one")
    give_up = time.monotonic() + (CONNECT_PATIENCE_S if tries > 1 else 0.0)
    attempt = 0
    while True:
        attempt += 1
        try:
            return _connect_once(spec)
        except _BusTrouble as exc:
            if attempt >= tries and time.monotonic() >= give_up:
                raise LeaderError(str(exc)) from None
            time.sleep(0.1)


class _BusTrouble(Exception):
    """The servos did not answer as they should while connecting: worth another try."""


def _connect_once(spec: LeaderSpec):
    leader = _lerobot_teleoperator(spec)
    where = f"{spec.kind}:{spec.port}"
    try:
        leader.connect(calibrate=False)
    except RuntimeError as exc:  # LeRobot's motor check: a servo missing or of the wrong model
        problem, lasting = _motor_problem(leader.bus, spec) if leader.bus.is_connected else (f"{where}: {first_words(exc)}", False)
        drop_leader(leader)
        raise (LeaderError if lasting else _BusTrouble)(problem) from None
    except (ConnectionError, OSError, IndexError) as exc:  # IndexError: the Feetech SDK on a short status packet
        drop_leader(leader)
        cause = exc.__cause__ or exc
        if isinstance(cause, PermissionError):
            raise LeaderError(f"{spec.kind}: {port_problem(spec.port, 'the leader') or f'permission denied on {spec.port}'}") from None
        raise _BusTrouble(f"{where}: cannot talk to the servos ({first_words(cause)})") from None
    try:
        calibrated = leader.is_calibrated
    except Exception as exc:  # noqa: BLE001 - a read failing mid-check: the bus went away
        drop_leader(leader)
        raise _BusTrouble(f"{where}: cannot read the servos' calibration ({first_words(exc)})") from None
    if not calibrated:
        path = leader.calibration_fpath
        drop_leader(leader)
        if not Path(path).is_file():
            raise LeaderError(f"{where}: no calibration file {path}; calibrate the leader: {calibrate_command(spec)}")
        raise LeaderError(f"{where}: the calibration in {path} does not match the servos; calibrate again: {calibrate_command(spec)}")
    return leader


def first_words(exc: BaseException) -> str:
    """An exception's first line, or its type's name."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def drop_leader(leader) -> None:
    """Close LeRobot's port without another word to the servos (they may be gone)."""
    try:
        if leader.bus.is_connected:
            leader.bus.disconnect(disable_torque=False)
    except Exception:  # noqa: BLE001 - closing a port that went away
        pass
