"""Placement tried over many seeds: a task file whose objects overlap on some seeds is refused up front.

`teleop run --seed S` places the objects from `default_rng(S)` at the robot's layout;
here the same placement runs for seeds 0..N-1 with every robot the task fits (no model is
built, so a few hundred seeds take well under a second per robot for most files).
"""

from __future__ import annotations

from collections import Counter
from typing import TYPE_CHECKING

import numpy as np

from scenes.tasks.file_values import TaskFileError

if TYPE_CHECKING:  # the robots and MuJoCo load when a check runs, not for `teleop --help`'s default
    from scenes.tasks.base import Task
    from scenes.tasks.file_task import FileTask

DEFAULT_SEEDS = 200  # `teleop scenes --seeds N`: a clash on 2% of seeds is missed with probability e^-4 ~ 2%


def placement_clashes(task: FileTask, robot: str, seeds: int) -> tuple[Counter, dict[tuple[str, str], int]]:
    """(seeds that failed per (object, the one it clashed with), the first such seed) at `robot`'s layout."""
    from scenes.assembly.build import layout_for
    from scenes.assembly.robot import load_robot
    from scenes.tasks.placement import PlacementError

    layout = layout_for(load_robot(robot))
    geos = task.geometries(layout)
    counts: Counter = Counter()
    first: dict[tuple[str, str], int] = {}
    for seed in range(seeds):
        try:
            task.place(layout, np.random.default_rng(seed), geos)
        except PlacementError as exc:
            counts[(exc.obj, exc.clash)] += 1
            first.setdefault((exc.obj, exc.clash), seed)
    return counts, first


def check_placement(task: Task, robots: list[str], seeds: int = DEFAULT_SEEDS) -> None:
    """TaskFileError (one line: the objects, the share of seeds, the first seed) if any seed cannot be placed."""
    from scenes.tasks.file_task import FileTask

    if not isinstance(task, FileTask) or seeds < 1:
        return
    for robot in robots:
        counts, first = placement_clashes(task, robot, seeds)
        if counts:
            (obj, clash), n = counts.most_common(1)[0]
            where = next(o.where for o in task.objects if o.name == obj)
            raise TaskFileError(f"{where}: region: cannot be placed apart from '{clash}' on {n} of {seeds} seeds "
                                f"({100 * n / seeds:.1f}%; first seed {first[(obj, clash)]}, robot {robot}): "
                                f"widen or separate the regions")
