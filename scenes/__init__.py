"""Robots and tasks: everything needed to compile a scene for a seed.

The names below load with their modules at first use (PEP 562): `scenes.errors` and the task files'
parsers do not pull in MuJoCo for a command that stops at a bad flag.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from scenes.lazy_names import lazy_names

if TYPE_CHECKING:
    from scenes.assembly.build import Scene, actuator_for_joint, build_scene
    from scenes.assembly.robot import BUILTIN_ROBOTS, ArmSpec, GripperSpec, Mount, RobotSpec, SceneError, load_robot
    from scenes.tasks.registry import TASKS

_HOMES = {
    "Scene": "scenes.assembly.build", "actuator_for_joint": "scenes.assembly.build", "build_scene": "scenes.assembly.build",
    "BUILTIN_ROBOTS": "scenes.assembly.robot", "ArmSpec": "scenes.assembly.robot", "GripperSpec": "scenes.assembly.robot",
    "Mount": "scenes.assembly.robot", "RobotSpec": "scenes.assembly.robot", "SceneError": "scenes.assembly.robot",
    "load_robot": "scenes.assembly.robot", "TASKS": "scenes.tasks.registry",
}

__all__ = [
    "ArmSpec", "BUILTIN_ROBOTS", "GripperSpec", "Mount", "RobotSpec", "Scene", "SceneError", "TASKS",
    "actuator_for_joint", "build_scene", "load_robot",
]


__getattr__, __dir__ = lazy_names(__name__, _HOMES, globals())
