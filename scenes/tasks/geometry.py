"""What a task stores in its compiled model, and the geometry read back from it.

The units (UNITS_NUMERIC: size, spread, reach in m, and the task's scale) and the task's
object bodies (OBJECTS_TEXT) live in the model itself, so a recording's model alone is
enough to judge it again. Boxes are in a body's own frame at the model's initial pose.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from scenes.tasks.expr import Number

if TYPE_CHECKING:  # MuJoCo loads with the first model read, not with a task file's parser
    import mujoco

UNITS_NUMERIC = "teleop_task_units"
OBJECTS_TEXT = "teleop_task_objects"  # custom text: the task's object bodies, comma-separated, in file order


@dataclass(frozen=True)
class Units:
    """Layout lengths (m) and the task's scale factor for plain numbers."""

    size: float
    spread: float
    reach: float
    scale: float = 1.0

    def length(self, n: Number) -> float:
        if n.unit in ("", "m"):
            return n.value * (self.scale if n.unit == "" else 1.0)
        return n.value * {"size": self.size, "spread": self.spread, "reach": self.reach}[n.unit]

    @staticmethod
    def angle(n: Number) -> float:
        return float(np.deg2rad(n.value)) if n.unit == "deg" else n.value

    def as_list(self) -> list[float]:
        return [self.size, self.spread, self.reach, self.scale]


def model_units(model: mujoco.MjModel) -> Units | None:
    """The units a task stored in the model, or None (a model from before task files)."""
    import mujoco

    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_NUMERIC, UNITS_NUMERIC)
    if i < 0:
        return None
    adr, size = int(model.numeric_adr[i]), int(model.numeric_size[i])
    values = model.numeric_data[adr:adr + size]
    return Units(*(float(v) for v in values[:4]))


def model_task_bodies(model: mujoco.MjModel) -> list[str] | None:
    """The body of each task object the scene stored in the model (fixed ones too), or None (a model from before)."""
    import mujoco

    i = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_TEXT, OBJECTS_TEXT)
    if i < 0:
        return None
    adr, size = int(model.text_adr[i]), int(model.text_size[i])
    text = bytes(model.text_data[adr:adr + size]).rstrip(b"\0").decode()
    return [n for n in text.split(",") if n]


def subtree(model: mujoco.MjModel, root: int) -> set[int]:
    """`root` and every body below it (MuJoCo numbers a body after its parent)."""
    out = {root}
    for b in range(root + 1, model.nbody):
        if int(model.body_parentid[b]) in out:
            out.add(b)
    return out


def colliding_geom(model: mujoco.MjModel, g: int) -> bool:
    """Whether geom `g` takes part in contacts (a contype or conaffinity bit set)."""
    return bool(model.geom_contype[g] or model.geom_conaffinity[g])


def body_box(model: mujoco.MjModel, bodies: set[int], frame_body: int, colliding: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) corners (m) of the box around `bodies`' geoms in `frame_body`'s frame at the model's initial pose."""
    import mujoco

    data = mujoco.MjData(model)
    mujoco.mj_kinematics(model, data)
    rot = data.xmat[frame_body].reshape(3, 3)
    origin = data.xpos[frame_body]
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for g in range(model.ngeom):
        if int(model.geom_bodyid[g]) not in bodies or (colliding and not colliding_geom(model, g)):
            continue
        if int(model.geom_type[g]) == int(mujoco.mjtGeom.mjGEOM_PLANE):
            continue
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        gmat = data.geom_xmat[g].reshape(3, 3)
        for corner in np.array(np.meshgrid([-1, 1], [-1, 1], [-1, 1])).T.reshape(-1, 3):
            world = data.geom_xpos[g] + gmat @ (center + corner * half)
            local = rot.T @ (world - origin)
            lo, hi = np.minimum(lo, local), np.maximum(hi, local)
    if not np.all(np.isfinite(lo)):
        lo = hi = np.zeros(3)
    return lo, hi
