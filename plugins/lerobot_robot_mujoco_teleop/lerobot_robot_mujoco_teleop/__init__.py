"""LeRobot's plugin entry for mujoco-teleop: importing it registers the robot `mujoco_teleop`, the teleoperator
`mujoco_teleop_web` and the env `mujoco_teleop` (the code: teleop/lerobot_plugin in mujoco-teleop).

Light: no MuJoCo, torch or viser is imported here (LeRobot imports this at every command's start)."""

import teleop.lerobot_plugin  # noqa: F401  (registers the three types)
