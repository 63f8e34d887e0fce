"""Camera framing: how many pixels across the smallest task object is at 96x96, over every task and robot.

Figures (`measure`), each task (built-in and library) built with each robot it fits,
seed 0, objects at their start and arms at home (scenes.cameras.figure):
  camera_front_object_px_at_96     the minimum over tasks and robots of the smallest object's projected
                                   width (px) in `front` at 96x96; goal >= 6
  camera_overhead_object_px_at_96  the same for `overhead`; goal >= 8
  camera_room_object_px_at_96      the same for `room` (the wide view, earlier scenes' `front`), for comparison
The task and robot that give each minimum go to stderr. Geometry only: nothing is rendered.
"""

from __future__ import annotations

import sys

from scenes.assembly.build import build_scene
from scenes.cameras.figure import camera_figures
from scenes.tasks.registry import TASKS, find_task, library_tasks

CAMERAS = ("front", "overhead", "room")


def figures_by_scene() -> dict[tuple[str, str], dict[str, float]]:
    """(task, robot) -> camera -> smallest object's width (px at 96x96), for every task and robot it lists."""
    out = {}
    for name in [*TASKS, *library_tasks()]:
        task = find_task(name)
        for robot in task.robots:
            out[(name, robot)] = camera_figures(build_scene(task, robot, seed=0))
    return out


def measure(quick: bool = False) -> dict[str, float]:
    table = figures_by_scene()
    results = {}
    for camera in CAMERAS:
        (task, robot), worst = min(((key, row[camera]) for key, row in table.items() if camera in row), key=lambda kv: kv[1])
        print(f"cameras: {camera}: smallest object {worst:g} px at 96x96 ({task} with {robot}; {len(table)} scenes)", file=sys.stderr)
        results[f"camera_{camera}_object_px_at_96"] = worst
    return results
