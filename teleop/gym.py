"""Gymnasium environments of the built-in scenes: importing this module registers them.

    import gymnasium, teleop.gym
    env = gymnasium.make("teleop/lift-panda-v0", action="ee_pose", image_size=(96, 96))
    env = teleop.gym.make_env("lift", "my_arm.toml", cameras=("front",))
    ids = teleop.gym.register("my_task.toml")  # ["teleop/my_task-panda-v0", ...]

One id per built-in scene and robot that can do it: `teleop/{scene}-{robot}-v0`
(bimanual scenes with the bimanual robot, single-arm scenes with single arms), and
one per library task and robot its file names (LIBRARY_ENV_IDS); `register(PATH)`
gives a task file of one's own its ids the same way.
Options (`gymnasium.make` keywords, or `make_env`'s): control_hz, cameras,
image_size (width, height), action (joint | ee_delta | ee_pose, as the export),
max_seconds, seed, render_mode ("rgb_array"). See `teleop.learn.gym_env.TeleopEnv`.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

import gymnasium

from scenes import BUILTIN_ROBOTS, TASKS, RobotSpec, load_robot
from scenes.tasks.registry import TaskFileError, find_task, library_tasks
from teleop.learn.gym_env import TeleopEnv

NAMESPACE = "teleop"
ENTRY_POINT = "teleop.learn.gym_env:TeleopEnv"


def env_id(scene: str, robot: str) -> str:
    return f"{NAMESPACE}/{scene}-{robot}-v0"


def builtin_pairs() -> list[tuple[str, str]]:
    """(scene, robot) for every built-in robot and every scene it can do."""
    pairs = []
    for robot in BUILTIN_ROBOTS:
        bimanual = load_robot(robot).bimanual
        pairs += [(scene, robot) for scene, task in TASKS.items() if task.supports(bimanual)]
    return pairs


def _register(pairs: list[tuple[str, str]]) -> list[str]:
    """Register (once) and list the ids of these (scene, robot) environments."""
    ids = []
    for scene, robot in pairs:
        name = env_id(scene, robot)
        if name not in gymnasium.registry:
            gymnasium.register(name, entry_point=ENTRY_POINT, kwargs={"scene": scene, "robot": robot})
        ids.append(name)
    return ids


def register_builtin() -> list[str]:
    """Register (once) and list the ids of the built-in scene x robot environments."""
    return _register(builtin_pairs())


ENV_IDS: list[str] = register_builtin()


def library_pairs() -> list[tuple[str, str]]:
    """(task, robot) for every library task file and every built-in robot its `robots` names."""
    pairs = []
    for name, path in library_tasks().items():
        robots = tomllib.loads(path.read_text()).get("robots") or [r for r in BUILTIN_ROBOTS if not load_robot(r).bimanual]
        pairs += [(name, robot) for robot in robots if robot in BUILTIN_ROBOTS]
    return pairs


def register_library() -> list[str]:
    """Register (once) and list the ids of the library's tasks (`teleop/{task}-{robot}-v0`), read lazily."""
    return _register(library_pairs())


LIBRARY_ENV_IDS: list[str] = register_library()


def register(path: str | Path) -> list[str]:
    """Register a task file's ids, `teleop/{its name}-{robot}-v0`, one per built-in robot it names that can
    do it (as the built-ins and the library are), and list them; registering the same file again changes
    nothing. TaskFileError (one line) for a bad file, or a name whose ids another task already holds."""
    path = Path(path).resolve()
    if not path.is_file():
        raise TaskFileError(f"{path}: no such task file")
    task = find_task(path)
    robots = [r for r in (task.robots or tuple(BUILTIN_ROBOTS)) if r in BUILTIN_ROBOTS]
    pairs = [(task.name, r) for r in robots if task.supports(load_robot(r).bimanual)]
    for name, robot in pairs:
        taken = gymnasium.registry.get(env_id(name, robot))
        if taken is not None and taken.kwargs.get("scene") != str(path):
            raise TaskFileError(f"{path}: name: {env_id(name, robot)} is already the id of {taken.kwargs.get('scene')!r}; "
                                f"give the task another name")
    ids = []
    for name, robot in pairs:
        ids.append(env_id(name, robot))
        if ids[-1] not in gymnasium.registry:
            gymnasium.register(ids[-1], entry_point=ENTRY_POINT, kwargs={"scene": str(path), "robot": robot})
    return ids


def make_env(scene: str | Path, robot: str | Path | RobotSpec = "panda", **options: Any) -> TeleopEnv:
    """An environment for any task (a name or a task file PATH.toml) and any robot, a built-in name or a PATH.toml brought by the user
    (not wrapped: Gymnasium's checker and order-enforcing wrappers come with `gymnasium.make`)."""
    return TeleopEnv(scene, robot, **options)
