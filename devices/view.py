"""What a device may look at while the session runs (read-only).

Devices sit upstream of the session, so they get this narrow view rather than
the session itself: enough for a script to aim at an object or for a device
to express deltas in the end-effector frame.
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
