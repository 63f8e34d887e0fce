"""Where a task file's objects start for one rng: drawn in their regions, in file order, never overlapping.

Offsets are in m from the workspace centre; an object `on` another is drawn relative to
it and stands on its top. Placement needs each object's footprint (file_geometry) but no
model, so checking many seeds is cheap.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from scenes.tasks.file_geometry import Geometry
from scenes.tasks.file_schema import ObjectDef
from scenes.tasks.file_values import TaskFileError, length, length_range
from scenes.tasks.geometry import Units

PLACE_TRIES = 1000

Box = tuple[tuple[float, float], tuple[float, float], tuple[float, float]]  # (x lo, hi), (y lo, hi) m; (yaw lo, hi) rad


@dataclass
class Placed:
    """Where placement put an object: centre offset (m, from the workspace centre), origin height, yaw."""

    xy: np.ndarray
    z: float
    yaw: float
    radius: float
    top: float  # height (m) of its top above the table
    on: str | None


class PlacementError(TaskFileError):
    """Objects that cannot be placed apart; `obj` and `clash` name the two."""

    def __init__(self, message: str, obj: str, clash: str) -> None:
        super().__init__(message)
        self.obj, self.clash = obj, clash


def place_boxes(obj: ObjectDef, regions: dict[str, dict], u: Units) -> list[Box]:
    """The boxes `obj` may be drawn in (a list of regions: one of them drawn per try)."""
    region = obj.raw.get("region")
    w = f"{obj.where}: region"
    out: list[Box] = []
    for one in region if isinstance(region, list) else [region]:
        if isinstance(one, str):
            reg = regions[one]
            out.append((length_range(reg["x"], u, f"{w} '{one}': x"), length_range(reg["y"], u, f"{w} '{one}': y"), (0.0, 0.0)))
            continue
        if one is None:
            one = {} if "on" in obj.raw else {"x": ["-1 spread", "1 spread"], "y": ["-1 spread", "1 spread"]}
        out.append((length_range(one.get("x", 0.0), u, f"{w}: x"), length_range(one.get("y", 0.0), u, f"{w}: y"),
                    length_range(one.get("yaw", 0.0), None, f"{w}: yaw")))
    return out


def min_distance(obj: ObjectDef, u: Units) -> float:
    """The `min_distance` (m) `obj` keeps from the others' centres, 0 when it sets none."""
    return length(obj.raw["min_distance"], u, f"{obj.where}: min_distance") if "min_distance" in obj.raw else 0.0


def place(objects: list[ObjectDef], geos: dict[str, Geometry], regions: dict[str, dict], gap: float, u: Units,
          rng: np.random.Generator) -> dict[str, Placed]:
    """Every object's place for this rng, in file order (PlacementError if one cannot be placed apart)."""
    placed: dict[str, Placed] = {}
    own_min = {obj.name: min_distance(obj, u) for obj in objects}
    for obj in objects:
        geo = geos[obj.name]
        on = obj.raw.get("on")
        min_d = own_min[obj.name]
        z_over = length(obj.raw["z"], u, f"{obj.where}: z") if "z" in obj.raw else None
        boxes = place_boxes(obj, regions, u)
        clash = ""
        for _ in range(PLACE_TRIES):
            (xl, xh), (yl, yh), (al, ah) = boxes[int(rng.integers(len(boxes)))] if len(boxes) > 1 else boxes[0]
            x = xl if xl == xh else float(rng.uniform(xl, xh))
            y = yl if yl == yh else float(rng.uniform(yl, yh))
            yaw = al if al == ah else float(rng.uniform(al, ah))
            base = placed[on] if on else None
            xy = (x + base.xy[0], y + base.xy[1]) if base is not None else (x, y)
            floor = base.top if base is not None else 0.0
            z = floor + (z_over if z_over is not None else geo.below)
            clash = ""
            if on is None:
                for other_name, other in placed.items():
                    if other.on is not None:
                        continue
                    need = max(geo.radius + other.radius + gap, min_d, own_min[other_name])
                    if math.hypot(xy[0] - other.xy[0], xy[1] - other.xy[1]) <= need:
                        clash = other_name
                        break
            if not clash:
                placed[obj.name] = Placed(np.array(xy), z, yaw, geo.radius, z + geo.above, on)
                break
        else:
            raise PlacementError(f"{obj.where}: region: cannot place it without overlapping '{clash}' ({PLACE_TRIES} tries)",
                                 obj.name, clash)
    return placed
