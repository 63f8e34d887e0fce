"""A leader arm's joint map: LeRobot's normalised joint readings -> a robot's joint angles (radians).

A map is a small TOML file, one per leader type in `devices/leader_maps/` (a user brings
their own with `map=FILE`). It names, for each leader joint, the robot joint it drives and
how LeRobot's number becomes radians:

  units = "degrees"   SO-10x leaders (LeRobot's `use_degrees=True`): q = sign * radians(value) + offset
  units = "range"     Koch leaders (LeRobot's -100..100 over the calibrated range): q runs linearly
                      from `at_minus_100` to `at_plus_100` (radians)

and the leader's gripper reading (LeRobot's 0..100) at `closed` and at `open`, which becomes
the robot's gripper opening 0 (closed) .. 1 (open). Every problem is one line naming the file
and the key.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from devices.base import DeviceError

MAPS_DIR = Path(__file__).parent / "leader_maps"
UNITS = ("degrees", "range")
_TOP_KEYS = {"leader", "robot", "units", "joints", "gripper"}
_RULE_KEYS = {"degrees": {"robot_joint", "sign", "offset"}, "range": {"robot_joint", "at_minus_100", "at_plus_100"}}
_GRIPPER_KEYS = {"leader_joint", "closed", "open"}


class JointMapError(DeviceError):
    """A joint map file that cannot be used; one line naming the file and the key."""


@dataclass(frozen=True)
class JointRule:
    """One leader joint -> one robot joint: q = scale * value + bias (radians)."""

    leader: str  # LeRobot's motor name ("shoulder_lift")
    robot: str  # the robot model's joint name
    scale: float  # radians per unit of LeRobot's reading
    bias: float  # radians at a reading of 0


@dataclass(frozen=True)
class GripperRule:
    """The leader's gripper reading (0..100) at closed and at open."""

    leader: str
    closed: float
    open: float

    def opening(self, value: float) -> float:
        """0 closed .. 1 open, clamped."""
        return min(max((value - self.closed) / (self.open - self.closed), 0.0), 1.0)


@dataclass(frozen=True)
class JointMap:
    """A loaded, checked map (see the module docstring)."""

    path: Path
    robot: str  # the robot whose joints the map names ("so101")
    units: str  # "degrees" or "range"
    joints: tuple[JointRule, ...]
    gripper: GripperRule | None
    leader: str = ""  # the leader type the file says it is for ("" if it does not say)

    @property
    def leader_joints(self) -> tuple[str, ...]:
        """Every LeRobot motor name the map reads."""
        return tuple(r.leader for r in self.joints) + ((self.gripper.leader,) if self.gripper else ())

    def robot_joints(self, reading: Mapping[str, float]) -> dict[str, float]:
        """Robot joint name -> radians, from LeRobot's reading {motor: value} (no ".pos" suffix)."""
        return {r.robot: r.scale * float(reading[r.leader]) + r.bias for r in self.joints}

    def gripper_opening(self, reading: Mapping[str, float]) -> float | None:
        """The gripper's opening 0..1 from the reading, or None when the map has no gripper."""
        return None if self.gripper is None else self.gripper.opening(float(reading[self.gripper.leader]))


def builtin_map_path(leader_type: str) -> Path:
    """The repository's map for a leader type ("so101_leader" -> devices/leader_maps/so101_leader.toml)."""
    return MAPS_DIR / f"{leader_type}.toml"


def _number(path: Path, where: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise JointMapError(f"{path}: {where} must be a finite number (got {value!r})")
    return float(value)


def _name(path: Path, where: str, value: object) -> str:
    if not isinstance(value, str) or not value.strip():
        raise JointMapError(f"{path}: {where} must be a joint name (got {value!r})")
    return value.strip()


def _unknown(path: Path, table: str, keys: set[str], allowed: set[str]) -> None:
    extra = sorted(keys - allowed)
    if extra:
        where = f"{table}.{extra[0]}" if table else extra[0]
        raise JointMapError(f"{path}: unknown key {where!r} (known: {', '.join(sorted(allowed))})")


def _rule(path: Path, units: str, leader: str, raw: object) -> JointRule:
    where = f"joints.{leader}"
    if not isinstance(raw, dict):
        raise JointMapError(f"{path}: {where} must be a table such as {{ robot_joint = \"{leader}\", ... }}")
    _unknown(path, where, set(raw), _RULE_KEYS[units])
    if "robot_joint" not in raw:
        raise JointMapError(f"{path}: {where} is missing 'robot_joint'")
    robot = _name(path, f"{where}.robot_joint", raw["robot_joint"])
    if units == "degrees":
        sign = _number(path, f"{where}.sign", raw.get("sign", 1))
        if sign not in (1.0, -1.0):
            raise JointMapError(f"{path}: {where}.sign must be 1 or -1 (got {raw['sign']!r})")
        offset = _number(path, f"{where}.offset", raw.get("offset", 0.0))
        return JointRule(leader, robot, sign * math.pi / 180.0, offset)
    for key in ("at_minus_100", "at_plus_100"):
        if key not in raw:
            raise JointMapError(f"{path}: {where} is missing {key!r} (radians at LeRobot's {key[3:].replace('_', ' ')})")
    lo = _number(path, f"{where}.at_minus_100", raw["at_minus_100"])
    hi = _number(path, f"{where}.at_plus_100", raw["at_plus_100"])
    if lo == hi:
        raise JointMapError(f"{path}: {where}: at_minus_100 and at_plus_100 must differ")
    return JointRule(leader, robot, (hi - lo) / 200.0, (hi + lo) / 2.0)


def _gripper(path: Path, raw: object) -> GripperRule:
    if not isinstance(raw, dict):
        raise JointMapError(f"{path}: gripper must be a table with leader_joint, closed and open")
    _unknown(path, "gripper", set(raw), _GRIPPER_KEYS)
    for key in ("closed", "open"):
        if key not in raw:
            raise JointMapError(f"{path}: gripper is missing {key!r} (the leader's 0..100 reading when {key})")
    closed = _number(path, "gripper.closed", raw["closed"])
    opened = _number(path, "gripper.open", raw["open"])
    if closed == opened:
        raise JointMapError(f"{path}: gripper.closed and gripper.open must differ")
    return GripperRule(_name(path, "gripper.leader_joint", raw.get("leader_joint", "gripper")), closed, opened)


def load_joint_map(path: Path | str) -> JointMap:
    """Read and check a map file; raises JointMapError (one line naming the file and the key)."""
    path = Path(path)
    if not path.is_file():
        raise JointMapError(f"{path}: no such joint map file")
    try:
        raw = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise JointMapError(f"{path}: not valid TOML ({exc})") from None
    except OSError as exc:
        raise JointMapError(f"{path}: cannot read ({exc.strerror or exc})") from None
    _unknown(path, "", set(raw), _TOP_KEYS)
    for key in ("robot", "units", "joints"):
        if key not in raw:
            raise JointMapError(f"{path}: missing required key {key!r}")
    robot = _name(path, "robot", raw["robot"])
    units = raw["units"]
    if units not in UNITS:
        raise JointMapError(f"{path}: units must be one of {', '.join(UNITS)} (got {units!r})")
    leader = raw.get("leader", "")
    if not isinstance(leader, str):
        raise JointMapError(f"{path}: leader must be a leader type such as \"so101_leader\"")
    table = raw["joints"]
    if not isinstance(table, dict) or not table:
        raise JointMapError(f"{path}: joints must be a table with one entry per leader joint")
    rules = tuple(_rule(path, units, name, value) for name, value in table.items())
    targets = [r.robot for r in rules]
    twice = sorted({t for t in targets if targets.count(t) > 1})
    if twice:
        raise JointMapError(f"{path}: joints: robot joint {twice[0]!r} is driven by more than one leader joint")
    gripper = _gripper(path, raw["gripper"]) if "gripper" in raw else None
    if gripper is not None and gripper.leader in table:
        raise JointMapError(f"{path}: gripper.leader_joint {gripper.leader!r} is also under joints")
    return JointMap(path=path, robot=robot, units=units, joints=rules, gripper=gripper, leader=leader)
