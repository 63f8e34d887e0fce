"""`--teleop.type=mujoco_teleop_web`: this tool's browser page as a LeRobot teleoperator (its config; the
teleoperator is mujoco_teleop_web.py).

Imported by teleop.lerobot_plugin once LeRobot's `lerobot.teleoperators.config` is loaded.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lerobot.teleoperators.config import TeleoperatorConfig

from teleop.lerobot_plugin import TELEOP_TYPE
from teleop.lerobot_plugin.options import check_rate


@TeleoperatorConfig.register_subclass(TELEOP_TYPE)
@dataclass(kw_only=True)
class MujocoTeleopWebConfig(TeleoperatorConfig):
    """scene / robot: the simulated arm whose IK turns the page's targets into joint targets (so101 drives a real
    SO-101 or the simulated one); fps: the page session's control rate; host / port: where the page is served
    (127.0.0.1 unless asked; port 0 picks a free one, printed on stderr); status_file: a JSON status file rewritten
    while serving, as `teleop serve --status-file` writes it (scripts and tests read the gizmo's target there), plus
    `lerobot_action`: the action get_action returns now (`tick`, `values`)."""

    scene: str = "lift"
    robot: str = "so101"
    fps: float = 30.0
    host: str = "127.0.0.1"
    port: int = 0
    status_file: Path | None = None

    def __post_init__(self) -> None:
        check_rate("fps", self.fps)
        if not (0 <= self.port <= 65535):
            raise ValueError(f"port must be 0 (any free port) or 1 to 65535 (got {self.port!r})")
