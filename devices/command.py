"""The one message every input device produces, and the session consumes.

Units are explicit so that a device never has to guess what "one step" means:
translations in metres, rotations in radians (axis-angle), both as deltas for
this control tick, in the frame named by `frame`. A device may instead (or as
well) give an absolute target pose in the world frame, or (a leader arm) joint
position targets in radians that the session applies without IK.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

Frame = Literal["world", "ee"]
GripperCommand = Literal["open", "close", "toggle"]
Event = Literal["reset", "start", "save", "discard", "record", "policy"]
# "record": start, or save when recording (one button on a pad); "policy": hand control back to a policy
EVENTS: tuple[str, ...] = ("reset", "start", "save", "discard", "record", "policy")


def _zeros3() -> np.ndarray:
    return np.zeros(3)


@dataclass
class Command:
    """What one device asks of one arm during one control tick.

    translation: metres to move the end-effector target this tick.
    rotation: axis-angle radians to rotate the target this tick.
    frame: "world" or "ee" (end-effector frame) for the two deltas.
    target_pos / target_quat: absolute world target (quat is wxyz); when set,
        the deltas are applied on top of it.
    gripper: "open", "close", "toggle" or None for no change.
    arm: which arm (0 unless bimanual).
    events: episode events raised this tick ("reset", "start", "save", "discard",
        "record": start or save), or "policy" (give control back to the policy driving
        a served session).
    source: the device's name, for logs and recordings.
    joints: joint position targets (radians, the arm's joints in the robot's own
        order: `SessionView.joint_names`), applied without IK and clamped to the
        joint ranges; the arm holds them until an end-effector command (a delta
        or an absolute target) arrives. The translation, rotation and target
        fields of a command that carries joints are not used.
    gripper_opening: 0 closed .. 1 open (clamped): sets the gripper actuator's
        ctrl linearly between its closed and open positions, until the next one
        or a `gripper` open/close/toggle.
    """

    translation: np.ndarray = field(default_factory=_zeros3)
    rotation: np.ndarray = field(default_factory=_zeros3)
    frame: Frame = "world"
    target_pos: np.ndarray | None = None
    target_quat: np.ndarray | None = None
    gripper: GripperCommand | None = None
    arm: int = 0
    events: tuple[str, ...] = ()
    source: str = ""
    joints: np.ndarray | None = None
    gripper_opening: float | None = None

    def is_idle(self) -> bool:
        """True when the command asks for nothing at all."""
        return (
            self.target_pos is None
            and self.target_quat is None
            and self.gripper is None
            and self.joints is None
            and self.gripper_opening is None
            and not self.events
            and not np.any(self.translation)
            and not np.any(self.rotation)
        )

    def to_dict(self) -> dict:
        """Plain JSON-able form, as stored in recordings."""
        return {
            "translation": [float(v) for v in self.translation],
            "rotation": [float(v) for v in self.rotation],
            "frame": self.frame,
            "target_pos": None if self.target_pos is None else [float(v) for v in self.target_pos],
            "target_quat": None if self.target_quat is None else [float(v) for v in self.target_quat],
            "gripper": self.gripper,
            "arm": int(self.arm),
            "events": list(self.events),
            "source": self.source,
            "joints": None if self.joints is None else np.ravel(np.asarray(self.joints, dtype=float)).tolist(),
            "gripper_opening": None if self.gripper_opening is None else float(self.gripper_opening),
        }
