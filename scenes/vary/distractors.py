"""Distractor objects: small boxes, cylinders and spheres on the table that no task is about.

Physical ones (generation) are free bodies that can be bumped; visual-only ones (a
look, at export) are world geoms that nothing collides with, so the recorded states
still fit the model (no body is added: the state's size stays). Both are placed on
the table around the work area, clear of the task's objects and the robots' bases,
as a pure function of the draws. Lengths are metres in the world frame.
"""

from __future__ import annotations

import colorsys
import math
from dataclasses import dataclass
from typing import Any

import mujoco
import numpy as np

from scenes.assembly.arena import TABLE_TOP
from scenes.tasks.geometry import model_units
from scenes.vary.variation import DISTRACTOR_PREFIX, Ranges, count, uniform

SHAPES = ("box", "cylinder", "sphere")
TRIES = 200  # placements tried per distractor before it is left out
DEFAULT_SIZE = 0.02  # m: the task-cube half-size of a model that stores no task units (Panda's)


@dataclass(frozen=True)
class Area:
    """Where distractors may stand: a box on the table (centre and half extents in x, y, m)."""

    center: tuple[float, float]
    half: tuple[float, float]
    size: float  # the task cube's half-size (m): distractor sizes are in these
    reach: float  # the robot's reach (m): how far to keep from its base


def area_of(model: mujoco.MjModel) -> Area:
    """The work area of a compiled scene: the model's stored layout units around its centre, inside the table."""
    units = model_units(model)
    size = units.size if units is not None else DEFAULT_SIZE
    spread = units.spread if units is not None else 0.15
    reach = units.reach if units is not None and units.reach > 0 else 0.85
    cx, cy = (float(v) for v in model.stat.center[:2])
    hx = hy = spread + 4 * size
    t = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_GEOM, "table")
    if t >= 0:  # keep on the table top
        tx, ty = model.geom_pos[t][:2]
        sx, sy = model.geom_size[t][:2]
        lo_x, hi_x = max(cx - hx, tx - sx + 2 * size), min(cx + hx, tx + sx - 2 * size)
        lo_y, hi_y = max(cy - hy, ty - sy + 2 * size), min(cy + hy, ty + sy - 2 * size)
        cx, cy, hx, hy = (lo_x + hi_x) / 2, (lo_y + hi_y) / 2, max(0.0, (hi_x - lo_x) / 2), max(0.0, (hi_y - lo_y) / 2)
    return Area((cx, cy), (hx, hy), size, reach)


def obstacles(model: mujoco.MjModel, data: mujoco.MjData, robot_roots: set[int], reach: float) -> list[tuple[float, float, float]]:
    """(x, y, radius) footprints to keep clear: each task body tree's geoms, and each robot's base (15 % of its reach)."""
    out = []
    for root in sorted({int(model.body_rootid[b]) for b in range(1, model.nbody)}):
        if root in robot_roots:
            x, y = data.xpos[root][:2]
            out.append((float(x), float(y), 0.15 * reach))
            continue
        for g in np.flatnonzero(model.body_rootid[model.geom_bodyid] == root):
            x, y = data.geom_xpos[g][:2]
            out.append((float(x), float(y), float(model.geom_rbound[g])))
    return out


def sample(rng: np.random.Generator, ranges: Ranges, area: Area, clear: list[tuple[float, float, float]]) -> list[dict[str, Any]]:
    """Distractors as JSON: name, shape, size (MuJoCo half sizes, m), pos (m, world) and rgba; the same draws, the same list."""
    out: list[dict[str, Any]] = []
    taken = list(clear)
    for i in range(count(rng, ranges.distractors)):
        shape = SHAPES[int(rng.integers(len(SHAPES)))]
        h = area.size * uniform(rng, ranges.distractor_size)
        if shape == "box":
            size = [h * float(rng.uniform(0.6, 1.4)), h * float(rng.uniform(0.6, 1.4)), h]
            radius, half_h = math.hypot(size[0], size[1]), h
        elif shape == "cylinder":
            size = [0.8 * h, h * float(rng.uniform(0.8, 1.8)), 0.0]
            radius, half_h = size[0], size[1]
        else:
            size = [h, 0.0, 0.0]
            radius, half_h = h, h
        r, g, b = colorsys.hsv_to_rgb(float(rng.random()), float(rng.uniform(0.3, 0.9)), float(rng.uniform(0.35, 0.95)))
        rgba = [round(r, 4), round(g, 4), round(b, 4), 1.0]
        yaw = float(rng.uniform(-math.pi, math.pi))
        (cx, cy), (hx, hy) = area.center, area.half
        for _ in range(TRIES):
            x, y = cx + float(rng.uniform(-hx, hx)), cy + float(rng.uniform(-hy, hy))
            if all(math.hypot(x - ox, y - oy) > radius + orad + area.size for ox, oy, orad in taken):
                taken.append((x, y, radius))
                out.append({"name": f"{DISTRACTOR_PREFIX}{i}", "shape": shape, "size": [round(v, 5) for v in size],
                            "pos": [round(x, 5), round(y, 5), round(TABLE_TOP + half_h, 5)], "yaw": round(yaw, 5), "rgba": rgba})
                break
    return out


_TYPES = {"box": mujoco.mjtGeom.mjGEOM_BOX, "cylinder": mujoco.mjtGeom.mjGEOM_CYLINDER, "sphere": mujoco.mjtGeom.mjGEOM_SPHERE}


def add(spec: mujoco.MjSpec, distractor: dict[str, Any], physical: bool) -> None:
    """Put one distractor into `spec`: a free body (physical) or a world geom nothing collides with (visual)."""
    d = distractor
    quat = [math.cos(d["yaw"] / 2), 0.0, 0.0, math.sin(d["yaw"] / 2)]
    geom = dict(type=_TYPES[d["shape"]], size=list(d["size"]), rgba=list(d["rgba"]))
    if physical:
        body = spec.worldbody.add_body(name=d["name"], pos=list(d["pos"]), quat=quat)
        body.add_freejoint(name=f"{d['name']}_joint")
        body.add_geom(name=f"{d['name']}_geom", density=500.0, condim=4, friction=[1.0, 0.01, 0.0005], **geom)
    else:
        spec.worldbody.add_geom(name=d["name"], pos=list(d["pos"]), quat=quat, contype=0, conaffinity=0, group=0, **geom)


__all__ = ["Area", "add", "area_of", "obstacles", "sample"]
