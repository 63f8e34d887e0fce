"""`--robot.type=mujoco_teleop`: the simulation as a LeRobot robot (its config; the robot is mujoco_teleop.py).

Imported by teleop.lerobot_plugin once LeRobot's `lerobot.robots.config` is loaded; LeRobot finds the robot
class `MujocoTeleop` from this module's name (config_mujoco_teleop -> mujoco_teleop).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from lerobot.robots.config import RobotConfig

from teleop.lerobot_plugin import ROBOT_TYPE
from teleop.lerobot_plugin.options import ACTION_SPACES, RECORD_FORMATS, check_choice, check_rate, check_seed, parse_image_size


@RobotConfig.register_subclass(ROBOT_TYPE)
@dataclass(kw_only=True)
class MujocoTeleopConfig(RobotConfig):
    """scene: a library task name or a task file PATH.toml; robot: panda, ur5e, so101, the two-arm rig or a PATH.toml;
    seed: the first episode's scene seed (each saved episode the next); fps: control ticks a second (one
    send_action steps the simulation 1/fps s); cameras: comma-separated scene cameras ('' for none);
    image_size: WIDTHxHEIGHT; action_space: joint | ee_delta; ee_step_m: metres per unit of an ee_delta
    teleoperator's delta (keyboard_ee and gamepad send -1/0/1); record_dir: also record this tool's own episodes
    there (record_format mcap | hdf5); view: serve this tool's session page on the simulation, watch-only, at
    view_host:view_port (127.0.0.1 unless asked; port 0 picks a free one; the URL on stderr)."""

    scene: str = "lift"
    robot: str = "so101"
    seed: int = 0
    fps: float = 30.0
    cameras: str = "front"
    image_size: str = "96x96"
    action_space: str = "joint"
    ee_step_m: float = 0.01
    record_dir: Path | None = None
    record_format: str = "mcap"
    view: bool = False
    view_host: str = "127.0.0.1"
    view_port: int = 0

    def __post_init__(self) -> None:
        # not RobotConfig's: it reads `cameras` as LeRobot camera configs; ours are the scene's camera names
        check_choice("action_space", self.action_space, ACTION_SPACES)
        check_choice("record_format", self.record_format, RECORD_FORMATS)
        check_rate("fps", self.fps)
        check_seed(self.seed)
        parse_image_size(self.image_size)
        if not (0 <= self.view_port <= 65535):
            raise ValueError(f"view_port must be 0 (any free port) or 1 to 65535 (got {self.view_port!r})")
        if not (self.ee_step_m > 0):
            raise ValueError(f"ee_step_m must be metres per delta unit, more than 0 (got {self.ee_step_m!r})")
