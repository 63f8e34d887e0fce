"""The part of the table a task uses, as world points the fixed cameras must keep in view.

A task file places each object's origin in a box (its `region`, relative to the
layout's workspace centre) and may name goal regions ([[region]]). The work area
is every such box grown by its object's footprint and raised to the object's top,
plus every goal region on the table. It does not depend on the seed, so cameras
framed on it are the same in every episode of a task. Lengths are metres, world frame.
"""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from scenes.assembly.arena import TABLE_TOP, Layout
from scenes.cameras.view import body_geoms, geom_corners
from scenes.tasks.base import Task
from scenes.tasks.file_task import FileTask
from scenes.tasks.file_values import length

Rect = tuple[float, float, float, float]  # x_lo, x_hi, y_lo, y_hi (m, from the workspace centre)


def _span(value: Any, task: FileTask, layout: Layout) -> tuple[float, float]:
    """A region's [lo, hi] (or one value) as lengths (m), read as the task file reads it."""
    units = task.units(layout)
    values = value if isinstance(value, list) else [value]
    lo, hi = (length(v, units, f"{task.where}: region") for v in (values[0], values[-1]))
    return min(lo, hi), max(lo, hi)


def _rect(entry: dict, task: FileTask, layout: Layout) -> Rect:
    x, y = _span(entry.get("x", 0.0), task, layout), _span(entry.get("y", 0.0), task, layout)
    return x[0], x[1], y[0], y[1]


def _region(obj_raw: dict) -> tuple[Any, bool]:
    """(the object's region as written, or the default spread box; whether its yaw is drawn)."""
    region = obj_raw.get("region")
    if region is None:
        region = {} if obj_raw.get("on") else {"x": ["-1 spread", "1 spread"], "y": ["-1 spread", "1 spread"]}
    yaw = region.get("yaw", 0.0) if isinstance(region, dict) else 0.0
    turns = isinstance(yaw, list) and len(yaw) == 2 and yaw[0] != yaw[1]
    return region, turns


def object_rects(task: FileTask, layout: Layout) -> dict[str, list[Rect]]:
    """Where each object's origin may start (boxes, m from the workspace centre); an object `on`
    another starts within the other's boxes shifted by its own."""
    out: dict[str, list[Rect]] = {}
    for obj in task.objects:
        region, _ = _region(obj.raw)
        names = [region] if isinstance(region, str) else region if isinstance(region, list) else None
        own = [_rect(task.regions[n], task, layout) for n in names] if names is not None else [_rect(region, task, layout)]
        on = obj.raw.get("on")
        if on and on in out:
            own = [(b[0] + r[0], b[1] + r[1], b[2] + r[2], b[3] + r[3]) for b in out[on] for r in own]
        out[obj.name] = own
    return out


def _footprint(model: mujoco.MjModel, data: mujoco.MjData, body: int, turns: bool) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) offsets (3,, m, world axes) of a body's visible geoms from its origin, and the origin's height
    folded into z; a body whose yaw is drawn gets the circle its corners sweep."""
    corners = geom_corners(model, data, body_geoms(model, body))
    if len(corners) == 0:
        corners = data.xpos[body][None, :]
    off = corners - data.xpos[body]
    lo, hi = off.min(axis=0), off.max(axis=0)
    if turns:
        r = float(np.max(np.linalg.norm(off[:, :2], axis=1)))
        lo[:2], hi[:2] = -r, r
    z = float(data.xpos[body][2]) - TABLE_TOP
    lo[2], hi[2] = max(0.0, z + lo[2]), z + hi[2]
    return lo, hi


def work_points(task: Task, layout: Layout, model: mujoco.MjModel) -> np.ndarray | None:
    """Corners (N x 3, m, world) of every object's start area (grown by its footprint, up to its top) and of
    every goal region. `model` is the task built into the arena (any seed: only shapes are read from it);
    None for a task that is not a task file (the cameras keep the layout's framing)."""
    if not isinstance(task, FileTask):
        return None
    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)  # qpos0: every object at its placed pose, its own joints at zero
    start = mujoco.MjData(model)
    for name, value in task.initial_joints().items():  # and as a reset leaves them (an open drawer, say)
        start.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, start)
    aliases = getattr(task, "aliases", {}) or {}
    cx, cy = layout.center
    rects = object_rects(task, layout)
    parts = []
    for obj in task.objects:
        bid = next((i for i in (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) for n in (obj.name, aliases.get(obj.name)) if n)
                    if i >= 0), -1)
        if bid < 0:
            continue
        turns = _region(obj.raw)[1]
        (lo0, hi0), (lo1, hi1) = _footprint(model, data, bid, turns), _footprint(model, start, bid, turns)
        lo, hi = np.minimum(lo0, lo1), np.maximum(hi0, hi1)
        for x0, x1, y0, y1 in rects[obj.name]:
            parts.append(np.array([[cx + x, cy + y, TABLE_TOP + z] for x in (x0 + lo[0], x1 + hi[0]) for y in (y0 + lo[1], y1 + hi[1])
                                   for z in (lo[2], hi[2])], float))
    for entry in task.regions.values():
        x0, x1, y0, y1 = _rect(entry, task, layout)
        parts.append(np.array([[cx + x, cy + y, TABLE_TOP] for x in (x0, x1) for y in (y0, y1)], float))
    return np.concatenate(parts) if parts else None
