"""What `teleop scenes` lists: every task (built-in, library, or a file given), and the robots it really builds with."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from scenes.assembly.build import build_scene
from scenes.cameras.figure import camera_figures
from scenes.errors import TeleopError, first_line
from scenes.assembly.robot import BUILTIN_ROBOTS, load_robot
from scenes.tasks.base import Task
from scenes.tasks.registry import BUILTIN_DIR, LIBRARY_DIR, TASKS, find_task, library_tasks
from scenes.tasks.seed_check import DEFAULT_SEEDS, check_placement


def object_names(task: Task) -> list[str]:
    objects = getattr(task, "objects", None)
    return [o.name for o in objects] if objects is not None else []


def describe(task: Task, check: bool = True, seeds: int = DEFAULT_SEEDS) -> dict[str, Any]:
    """One task's row: instruction(s), family, objects, the robots it fits (built and compiled when `check`)
    and, when checked, each camera's `object_px_at_96` (scenes.cameras.figure; the smallest over the robots).
    When checked, placement is tried on seeds 0..seeds-1 with every robot it fits (TaskFileError if one fails)."""
    wanted = list(task.robots) or [r for r in BUILTIN_ROBOTS if task.supports(load_robot(r).bimanual)]
    fits, failed = [], {}
    figures: dict[str, dict[str, float]] = {}  # camera -> robot -> px
    for robot in wanted:
        if not check:
            fits.append(robot)
            continue
        try:
            scene = build_scene(task, robot, seed=0)
            fits.append(robot)
        except TeleopError as exc:
            failed[robot] = first_line(exc)
            continue
        for camera, px in camera_figures(scene).items():
            figures.setdefault(camera, {})[robot] = px
    if check:
        check_placement(task, fits, seeds)
    path = getattr(task, "path", None)
    where = "builtin" if path is not None and Path(path).parent == BUILTIN_DIR else (
        "library" if path is not None and Path(path).parent == LIBRARY_DIR else str(path or ""))
    row: dict[str, Any] = {
        "name": task.name, "instruction": task.text, "instructions": list(task.instructions), "family": task.family,
        "summary": task.summary, "objects": object_names(task), "subtasks": [s.object for s in task.subtasks],
        "robots": fits, "source": where,
        "arms": "bimanual" if task.needs_bimanual else ("single or bimanual" if task.allows_bimanual else "single"),
    }
    if check:
        row["cameras"] = {camera: {"object_px_at_96": min(by.values()), "by_robot": by} for camera, by in figures.items()}
    if failed:
        row["robots_failing"] = failed
    return row


def catalog(paths: list[str | Path] | None = None, check: bool = True, seeds: int = DEFAULT_SEEDS) -> list[dict[str, Any]]:
    """Rows for the given task files, or for every built-in and library task (`seeds`: placement seeds tried)."""
    if paths:
        return [describe(find_task(p if str(p).endswith(".toml") else Path(p)), check, seeds) for p in paths]
    tasks: list[Task] = list(TASKS.values()) + [find_task(name) for name in library_tasks()]
    return [describe(t, check, seeds) for t in tasks]
