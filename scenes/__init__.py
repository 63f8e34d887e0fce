"""Robots and tasks: everything needed to compile a scene for a seed.

The names below load with their modules at first use (PEP 562): `scenes.errors` and the task files'
parsers do not pull in MuJoCo for a command that stops at a bad flag.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

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


def __getattr__(name: str) -> Any:
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module 'scenes' has no attribute {name!r}")
    value = getattr(importlib.import_module(home), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
