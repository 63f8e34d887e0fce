"""Tasks: the five built-in task files, the library, and how a scene name or a PATH.toml finds its task.

Every task is a task file (scenes.tasks.file_task): the built-in five ship in
scenes/builtin_tasks/, the library's in scenes/library/. A task adds its bodies to the
arena spec (so the compiled model is one honest MJCF, no string pasting) and
judges success from MjData alone, so that a recording can be judged again at replay.
"""

from __future__ import annotations

from collections.abc import Mapping
from functools import lru_cache
from pathlib import Path
from typing import Any

from scenes.assembly.robot import SceneError
from scenes.tasks.base import SUBTASK_KINDS, SubtaskKind, SubtaskSpec, Task, object_pose
from scenes.tasks.file_task import FileTask, load_task_file, task_from_bundle
from scenes.tasks.file_values import TaskFileError

BUILTIN_DIR = Path(__file__).resolve().parent.parent / "builtin_tasks"
LIBRARY_DIR = Path(__file__).resolve().parent.parent / "library"
BUILTIN_ORDER = ("lift", "stack", "pick_place", "door", "handover")
TASK_FILE_KEY = "task_file"  # episode metadata key holding FileTask.bundle()
INSTRUCTION_INDEX_KEY = "instruction_index"  # episode metadata key: which of [instruction] + instructions was used

__all__ = [
    "BUILTIN_DIR", "FileTask", "INSTRUCTION_INDEX_KEY", "LIBRARY_DIR", "SUBTASK_KINDS", "SubtaskKind", "SubtaskSpec", "TASKS",
    "TASK_FILE_KEY", "Task", "TaskFileError", "episode_extra", "find_task", "library_tasks", "object_pose", "task_for_episode",
]

TASKS: dict[str, Task] = {name: load_task_file(BUILTIN_DIR / f"{name}.toml") for name in BUILTIN_ORDER}


@lru_cache(maxsize=1)
def _library() -> dict[str, Path]:
    return {p.stem: p for p in sorted(LIBRARY_DIR.glob("*.toml"))}


def library_tasks() -> dict[str, Path]:
    """The library's task files by name (scenes/library/*.toml), loaded on demand with find_task."""
    return dict(_library())


def is_task_path(scene: str | Path) -> bool:
    return str(scene).endswith(".toml") or (isinstance(scene, Path) and scene.exists())


def find_task(scene: str | Path | Task) -> Task:
    """The task a `--scene` value names: a built-in name, a library name, or a PATH.toml."""
    if isinstance(scene, Task):
        return scene
    if is_task_path(scene):
        return load_task_file(Path(scene))
    name = str(scene)
    if name in TASKS:
        return TASKS[name]
    if name in _library():
        return _cached_library_task(name)
    raise SceneError(f"unknown scene {name!r} (built-ins: {', '.join(TASKS)}; `teleop scenes` lists the library; or give a task .toml file)")


@lru_cache(maxsize=64)
def _cached_library_task(name: str) -> FileTask:
    return load_task_file(_library()[name])


def episode_extra(task: Task, seed: int) -> dict[str, Any]:
    """What an episode stores about its task besides `task`: the task file bundle and which instruction was used."""
    out: dict[str, Any] = {INSTRUCTION_INDEX_KEY: task.instruction_for(seed)[1]}
    if isinstance(task, FileTask):
        out[TASK_FILE_KEY] = task.bundle()
    return out


def task_for_episode(scene: str, extra: Mapping[str, Any] | None = None) -> Task:
    """The task an episode was recorded with: from its embedded task file when it has one, else by name."""
    bundle = (extra or {}).get(TASK_FILE_KEY)
    if bundle:
        return task_from_bundle(bundle)
    return find_task(scene)
