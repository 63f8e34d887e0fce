"""The robot's joints as LeRobot features: names and units, both ways (no LeRobot, no MuJoCo here).

Each arm joint is `<joint>.pos` and each gripper `<prefix>gripper.pos`, in the order of this tool's export
(`observation.state`'s names). The so101 speaks LeRobot's `so101_follower` units, so that its leader drives
it with no mapping and a dataset recorded on the simulation has the real arm's features:
joints in degrees (LeRobot's `use_degrees`: 0 at the calibrated middle, which is the model's q = 0, as
devices/leader_maps/so101_leader.toml says) and the gripper 0 (closed) .. 100 (open). Every other robot
speaks this tool's export units: radians (metres for a slide joint) and the gripper 0 (closed) .. 1 (open).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

# LeRobot's so101_follower motor names, which are the sim so101's joint names (and its gripper actuator's)
SO101_MOTORS = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll", "gripper")


@dataclass(frozen=True)
class JointUnits:
    """One state entry: its export name, whether it is a gripper, and LeRobot's scale for it."""

    name: str  # export name ("elbow_flex", "left/gripper")
    gripper: bool
    scale: float  # LeRobot units per export unit (degrees per radian, or 100 per gripper opening)

    @property
    def key(self) -> str:
        return f"{self.name}.pos"


@dataclass(frozen=True)
class RobotUnits:
    """Every state entry of a robot, in export order, and the units they are spoken in."""

    entries: tuple[JointUnits, ...]
    so101: bool  # LeRobot's so101_follower units (degrees, gripper 0..100); else radians and 0..1

    @classmethod
    def of(cls, state_names: Sequence[str], gripper_names: Sequence[str], robot_name: str) -> RobotUnits:
        so101 = robot_name == "so101" and tuple(state_names) == SO101_MOTORS
        entries = tuple(
            JointUnits(n, n in gripper_names, (100.0 if n in gripper_names else 180.0 / math.pi) if so101 else 1.0)
            for n in state_names
        )
        return cls(entries, so101)

    @property
    def keys(self) -> list[str]:
        return [e.key for e in self.entries]

    def to_lerobot(self, state: Sequence[float]) -> dict[str, float]:
        """Export-unit values (rad, gripper 0..1) -> {"<name>.pos": LeRobot units}."""
        return {e.key: float(v) * e.scale for e, v in zip(self.entries, state)}

    def from_lerobot(self, action: Mapping[str, float]) -> list[float]:
        """{"<name>.pos": LeRobot units} -> export-unit values; ValueError naming a missing or non-finite key."""
        missing = [e.key for e in self.entries if e.key not in action]
        if missing:
            raise ValueError(f"the action lacks {', '.join(missing)} (this robot's action keys: {', '.join(self.keys)})")
        values = [float(action[e.key]) / e.scale for e in self.entries]
        bad = [e.key for e, v in zip(self.entries, values) if not math.isfinite(v)]
        if bad:
            raise ValueError(f"the action's {', '.join(bad)} is not a finite number")
        return values
