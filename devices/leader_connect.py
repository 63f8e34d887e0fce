"""A leader arm's `--device` word and its connection through LeRobot's own teleoperator classes.

`so101_leader:PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]` (and `so100_leader`,
`koch_leader`) becomes a LeaderSpec; `connect_leader` checks the port, the servos and the calibration, then
opens it with LeRobot's `connect(calibrate=False)` (LeRobot's own `calibrate()` waits on stdin), the way a
follower is connected too (devices/lerobot_connect.py), so that every fault is one line (LeaderError) before
anything runs. LeRobot and its servo SDKs are imported only
here, when a leader starts (the `hardware` extra). The device that reads it is devices.lerobot_leader.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from devices.base import DeviceError
from devices.serial_ports import port_problem
from scenes.errors import first_line
from scenes.numbers import number_or_nan

if TYPE_CHECKING:  # annotations only: devices.lerobot_connect loads when a leader connects
    from devices.lerobot_connect import ArmWords

LEADER_TYPES = ("so101_leader", "so100_leader", "koch_leader")
MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")  # LeRobot's names, ids 1-6
UNITS = {"so101_leader": "degrees", "so100_leader": "degrees", "koch_leader": "range"}  # LeRobot's normalisation
OPTION_KEYS = ("id", "calibration", "map", "scale", "arm")
SPEC_HELP = "PORT[:id=NAME][:calibration=DIR][:map=FILE][:scale=F][:arm=K]"
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
            f"{spec.kind}:{spec.port}: cannot read the calibration file ({type(exc).__name__}: {first_line(exc)}); "
            f"calibrate again: {calibrate_command(spec)}"
        ) from None


def leader_words(spec: LeaderSpec) -> ArmWords:
    """How the connect's messages name this leader."""
    from devices.lerobot_connect import ArmWords

    return ArmWords(where=f"{spec.kind}:{spec.port}", what="the leader", model_of=f"a {spec.kind}",
                    calibrate=calibrate_command(spec))


def connect_leader(spec: LeaderSpec, patient: bool = True):
    """LeRobot's teleoperator for the spec, checked and connected without calibrating (devices/lerobot_connect.py,
    the follower's way too); LeaderError otherwise.

    `patient` False: one quick try (a leader reopened every second after an unplug).
    """
    problem = port_problem(spec.port, "the leader")
    if problem:
        raise LeaderError(f"{spec.kind}: {problem}")
    if spec.calibration is not None and not spec.calibration.is_dir():
        raise LeaderError(f"{spec.kind}:{spec.port}: calibration={spec.calibration} is not a folder; {calibrate_command(spec)} writes one")
    from devices.lerobot_connect import ArmError, connect_arm

    leader = _lerobot_teleoperator(spec)
    try:
        connect_arm(leader, leader_words(spec), energises=False, patient=patient)
    except ArmError as exc:
        raise LeaderError(str(exc)) from None
    return leader


def drop_leader(leader) -> None:
    """Close LeRobot's port without another word to the servos (they may be gone)."""
    from devices.lerobot_connect import release

    release(leader, torque_off=False)
