"""What `--follower` names, and how the simulated arm's joint targets become a follower's numbers (issue 47).

`TYPE:PORT[:id=NAME][:calibration=DIR][:map=FILE][:max_step=DEG]` is parsed here, with no serial port opened
and no LeRobot loaded, so a bad flag (a `map=` file that does not exist included) stops a command in one line
before anything starts. The motor map is a leader's joint map inverted, so a leader and a follower agree on
every joint angle: the follower's own `map=FILE`, else the `map=` of the SO-10x leader that drives the same arm
(`leader_map_of`: a user who flipped a joint's sign for their leader has the follower flip it back), else the
paired leader type's map in devices/leader_maps. The follower itself (its thread, LeRobot's `SOFollower`) is
teleop/control/follower.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from devices.base import DeviceError
from devices.leader_connect import LEADER_TYPES, UNITS, LeaderError, parse_leader_spec
from devices.joint_map import GripperRule, JointMap, JointMapError, JointRule, builtin_map_path, load_joint_map
from scenes.numbers import number_or_nan
from teleop.errors import UsageError

# follower type -> (the simulated robot it mirrors, the leader type whose joint map it shares)
FOLLOWERS: dict[str, tuple[str, str]] = {"so101_follower": ("so101", "so101_leader")}
DEFAULT_MAX_STEP_DEG = 5.0  # degrees per tick
SPEC_KEYS = ("id", "calibration", "map", "max_step")


@dataclass(frozen=True)
class FollowerSpec:
    """A parsed `--follower` value. max_step_deg: the largest change per joint per tick, degrees."""

    kind: str
    port: str
    id: str | None = None
    calibration: Path | None = None
    max_step_deg: float = DEFAULT_MAX_STEP_DEG
    map: Path | None = None  # the joint map (degrees) to invert; None: the driving leader's, else the built-in

    @property
    def robot(self) -> str:
        """The simulated robot this follower can mirror."""
        return FOLLOWERS[self.kind][0]

    def calibrate_hint(self) -> str:
        """The LeRobot command that writes this follower's calibration file."""
        where = f" --robot.calibration_dir={self.calibration}" if self.calibration is not None else ""
        return (f"lerobot-calibrate --robot.type={self.kind} --robot.port={self.port} "
                f"--robot.id={self.id or 'ID'}{where}" + ("" if self.id else " (and add :id=ID to --follower)"))


def parse_follower_spec(text: str) -> FollowerSpec:
    """`TYPE:PORT[:id=NAME][:calibration=DIR][:map=FILE][:max_step=DEG]`; a UsageError (one line) names what is wrong."""
    kind, _, rest = text.partition(":")
    kind = kind.strip().lower()
    if kind not in FOLLOWERS:
        raise UsageError(f"--follower {text}: unknown follower type {kind!r} (known: {', '.join(FOLLOWERS)})")
    parts = rest.split(":") if rest else []
    if not parts or not parts[0].strip() or "=" in parts[0]:
        raise UsageError(f"--follower {text}: give the serial port, e.g. {kind}:/dev/ttyACM0")
    options: dict[str, str] = {}
    for part in parts[1:]:
        key, eq, value = part.partition("=")
        key = key.strip()
        if not eq or key not in SPEC_KEYS or not value.strip():
            raise UsageError(f"--follower {text}: {part!r} is not one of {', '.join(k + '=...' for k in SPEC_KEYS)}")
        options[key] = value.strip()
    max_step = DEFAULT_MAX_STEP_DEG
    if "max_step" in options:
        max_step = number_or_nan(options["max_step"])
        if not (math.isfinite(max_step) and 0 < max_step <= 90):
            raise UsageError(f"--follower {text}: max_step must be degrees per tick, more than 0 and at most 90")
    calibration = Path(options["calibration"]).expanduser() if "calibration" in options else None
    map_path = Path(options["map"]).expanduser() if "map" in options else None
    if map_path is not None and not map_path.is_file():  # never the built-in quietly in its place
        raise UsageError(f"--follower {text}: map={map_path}: no such joint map file")
    return FollowerSpec(kind, parts[0].strip(), options.get("id"), calibration, max_step, map_path)


def check_pairing(spec: FollowerSpec, robot_name: str) -> None:
    """A follower mirrors only its own simulated robot (an so101_follower the so101)."""
    if robot_name != spec.robot:
        raise UsageError(f"--follower {spec.kind} mirrors the simulated {spec.robot}, not {robot_name!r}: "
                         f"add --robot {spec.robot}")


# --- simulated joints -> LeRobot's numbers ----------------------------------------------------------------

@dataclass(frozen=True)
class MotorMap:
    """The simulated arm's joint targets (radians) -> LeRobot's action {"motor.pos": degrees, gripper 0..100}.

    The inverse of the leader's map (q = scale * value + bias), so a leader and a follower agree on
    what each robot joint angle is on a real arm.
    """

    joints: tuple[JointRule, ...]  # in the robot's joint order
    gripper: GripperRule | None
    source: str  # where the map came from, for messages

    @property
    def motors(self) -> tuple[str, ...]:
        return tuple(r.leader for r in self.joints) + ((self.gripper.leader,) if self.gripper else ())

    def values(self, q: np.ndarray, opening: float | None) -> list[float]:
        """LeRobot's numbers for joint targets `q` (rad, robot order) and a gripper opening 0..1 (None: no gripper)."""
        out = [(float(v) - r.bias) / r.scale for r, v in zip(self.joints, q)]
        if self.gripper is not None:
            g = self.gripper
            o = 0.0 if opening is None else min(max(opening, 0.0), 1.0)
            out.append(g.closed + o * (g.open - g.closed))
        return out


def default_leader_map(leader: str, joint_names: tuple[str, ...]) -> JointMap:
    """The map an SO-10x leader would use if its file were missing: LeRobot's degrees are the robot's angles."""
    rules = tuple(JointRule(n, n, math.pi / 180.0, 0.0) for n in joint_names)
    return JointMap(path=Path("<built-in>"), robot="so101", units="degrees", joints=rules,
                    gripper=GripperRule("gripper", 0.0, 100.0), leader=leader)


def leader_map_of(devices: str | None, arm: int = 0, n_arms: int = 1) -> Path | None:
    """The `map=FILE` of the SO-10x leader among the `--device` words that drives `arm`, or None.

    A Koch leader's map reads -100..100 of another arm: a follower keeps its own. A leader word that does not
    parse gives None here: the leader itself says what is wrong when it opens.
    """
    for word in (devices or "").split(","):
        kind, _, arg = word.strip().partition(":")
        kind = kind.strip().lower()
        if kind not in LEADER_TYPES or UNITS[kind] != "degrees":
            continue
        try:
            spec = parse_leader_spec(kind, arg, n_arms)
        except LeaderError:
            continue
        if spec.arm == arm and spec.map is not None:
            return spec.map
    return None


def motor_map(spec: FollowerSpec, joint_names: tuple[str, ...], leader_map: Path | None = None) -> MotorMap:
    """The follower's map for the simulated arm's joints, inverted: its own `map=`, else the driving leader's
    (`leader_map`), else the paired leader type's file."""
    leader = FOLLOWERS[spec.kind][1]
    path = spec.map or leader_map or builtin_map_path(leader)
    try:
        if spec.map is None and leader_map is None and not path.is_file():
            joint_map = default_leader_map(leader, joint_names)
        else:
            joint_map = load_joint_map(path)  # a file that is not there: one line, never the built-in in its place
    except JointMapError as exc:
        raise DeviceError(str(exc)) from None
    if joint_map.units != "degrees":
        raise DeviceError(f"{joint_map.path}: a follower needs a map in degrees, not {joint_map.units!r}")
    by_robot = {r.robot: r for r in joint_map.joints}
    missing = [n for n in joint_names if n not in by_robot]
    if missing:
        raise DeviceError(f"{joint_map.path}: no leader joint drives the robot joint {missing[0]!r}")
    return MotorMap(tuple(by_robot[n] for n in joint_names), joint_map.gripper, str(joint_map.path))
