"""What a device may look at while the session runs (read-only).

Devices sit upstream of the session, so they get this narrow view rather than
the session itself: enough for a script to aim at an object, for a device
to express deltas in the end-effector frame, or for a leader arm to ease in
from the simulated arm's joints and map onto them.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np


class SessionView(Protocol):
    """Read-only facts about the running session."""

    @property
    def time(self) -> float:
        """Simulated seconds since the episode began."""
        ...

    @property
    def n_arms(self) -> int: ...

    def ee_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Actual end-effector (position, wxyz quaternion) in the world frame."""
        ...

    def target_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """Current end-effector target (position, wxyz quaternion)."""
        ...

    def body_pos(self, name: str) -> np.ndarray:
        """World position of a body; raises KeyError naming the body if unknown."""
        ...

    def body_quat(self, name: str) -> np.ndarray:
        """World orientation (wxyz quaternion) of a body; raises KeyError naming the body if unknown."""
        ...

    @property
    def robot_name(self) -> str:
        """The robot's name (`teleop robots`: "so101", "panda", ...)."""
        ...

    @property
    def reach(self) -> float:
        """Metres from an arm's first joint that its end-effector can reach."""
        ...

    def joint_names(self, arm: int = 0) -> tuple[str, ...]:
        """The arm's joints in the robot's own order, as the robot's model names them (no mount prefix)."""
        ...

    def joint_positions(self, arm: int = 0) -> np.ndarray:
        """The arm's joint positions now (radians, `joint_names` order)."""
        ...

    def joint_targets(self, arm: int = 0) -> np.ndarray:
        """The arm's joint position targets now, its actuators' ctrl (radians, `joint_names` order)."""
        ...

    def joint_limits(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(low, high) arrays of the arm joints' ranges (radians; -inf / inf where a joint is unlimited)."""
        ...

    def base_pose(self, arm: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """World (position m, wxyz quaternion) of the arm's base body (the one its first joint's link is mounted on)."""
        ...
