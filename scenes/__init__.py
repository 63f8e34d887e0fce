"""Robots and tasks: everything needed to compile a scene for a seed."""

from scenes.assembly.build import Scene, actuator_for_joint, build_scene
from scenes.assembly.robot import BUILTIN_ROBOTS, ArmSpec, GripperSpec, Mount, RobotSpec, SceneError, load_robot
from scenes.tasks.registry import TASKS

__all__ = [
    "ArmSpec", "BUILTIN_ROBOTS", "GripperSpec", "Mount", "RobotSpec", "Scene", "SceneError", "TASKS",
    "actuator_for_joint", "build_scene", "load_robot",
]
