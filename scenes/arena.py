"""The room every task shares: floor, table, lights and the fixed cameras.

Everything is sized from the robot's reach so that a 0.35 m SO-101 and a
0.85 m Panda both get a table they can work on and cameras that frame it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

TABLE_TOP = 0.0  # world z of the table surface; robots stand on it


@dataclass(frozen=True)
class Layout:
    """Where the work happens, derived from the robot."""

    center: tuple[float, float]  # workspace centre on the table (x, y)
    spread: float  # half-width of the area objects are placed in
    size: float  # half-size of a task cube
    table_half: tuple[float, float]  # table half extents (x, y)
    table_center: tuple[float, float]
    bimanual: bool
    reach: float = 0.0  # the robot's reach (m), a length unit task files may use


def make_arena(layout: Layout, timestep: float, spec: mujoco.MjSpec | None = None) -> mujoco.MjSpec:
    """Add floor, table, lights, cameras and physics options to `spec` (or a new one).

    A single-arm robot's own spec is the base (the arm stays at the origin, its
    names untouched); bimanual arms are attached into a fresh spec under prefixes.
    """
    spec = spec if spec is not None else mujoco.MjSpec()
    spec.modelname = "teleop_scene"
    spec.compiler.degree = False
    spec.option.timestep = timestep
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 10.0
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    spec.visual.headlight.ambient = [0.25, 0.25, 0.25]
    spec.visual.headlight.diffuse = [0.35, 0.35, 0.35]
    spec.stat.center = [layout.center[0], layout.center[1], 0.2]
    spec.stat.extent = 1.5

    grid = spec.add_texture(
        name="grid", type=mujoco.mjtTexture.mjTEXTURE_2D, builtin=mujoco.mjtBuiltin.mjBUILTIN_CHECKER,
        rgb1=[0.32, 0.34, 0.38], rgb2=[0.26, 0.28, 0.31], width=256, height=256,
    )
    floor_mat = spec.add_material(name="floor", texrepeat=[6, 6], reflectance=0.05)
    floor_mat.textures[mujoco.mjtTextureRole.mjTEXROLE_RGB] = grid.name
    wood = spec.add_material(name="table", rgba=[0.62, 0.5, 0.38, 1.0])
    leg_height = 0.75

    world = spec.worldbody
    world.add_light(pos=[layout.center[0], layout.center[1], 2.5], dir=[0, 0, -1], diffuse=[0.55, 0.55, 0.55],
                    specular=[0.05, 0.05, 0.05], castshadow=True)
    world.add_light(pos=[-1.5, -1.5, 2.0], dir=[0.5, 0.5, -0.7], diffuse=[0.3, 0.3, 0.3], specular=[0.05, 0.05, 0.05], castshadow=False)
    world.add_geom(
        name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[0, 0, 0.05],
        pos=[0, 0, TABLE_TOP - leg_height], material=floor_mat.name,
    )
    hx, hy = layout.table_half
    cx, cy = layout.table_center
    world.add_geom(
        name="table", type=mujoco.mjtGeom.mjGEOM_BOX, size=[hx, hy, 0.02],
        pos=[cx, cy, TABLE_TOP - 0.02], material=wood.name, friction=[1.0, 0.005, 0.0001],
    )
    for sx in (-1, 1):
        for sy in (-1, 1):
            world.add_geom(
                type=mujoco.mjtGeom.mjGEOM_BOX, size=[0.03, 0.03, (leg_height - 0.04) / 2],
                pos=[cx + sx * (hx - 0.05), cy + sy * (hy - 0.05), TABLE_TOP - 0.04 - (leg_height - 0.04) / 2],
                material=wood.name, contype=0, conaffinity=0,
            )
    _add_cameras(world, layout)
    return spec


def look_at_xyaxes(eye: np.ndarray, target: np.ndarray) -> list[float]:
    """xyaxes for a camera at `eye` looking at `target` with world z up."""
    forward = target - eye
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:
        right = np.array([0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    return [*right, *up]


def _add_cameras(world: mujoco.MjsBody, layout: Layout) -> None:
    """`front` frames the robot and the workspace; `overhead` looks straight down on the workspace."""
    cx, cy = layout.center
    dist = max(0.6, 2.2 * layout.spread + 0.45)
    if layout.bimanual:
        target = np.array([cx, cy, TABLE_TOP + 0.1])
        front_eye = np.array([cx, cy - 1.5 * dist, TABLE_TOP + 0.9 * dist])
    else:
        target = np.array([0.6 * cx, cy, TABLE_TOP + 0.35 * cx])
        front_eye = np.array([cx + 1.5 * dist, cy + 0.6 * dist, TABLE_TOP + 0.9 * dist])
    world.add_camera(name="front", pos=front_eye, xyaxes=look_at_xyaxes(front_eye, target), fovy=50)
    over_eye = np.array([cx, cy, TABLE_TOP + 1.5 * dist])
    world.add_camera(name="overhead", pos=over_eye, xyaxes=[0, -1, 0, 1, 0, 0] if not layout.bimanual else [1, 0, 0, 0, 1, 0], fovy=45)


def reference_layout() -> Layout:
    """The layout of a 0.85 m reach arm with 0.02 m cubes (Panda): task files are checked against it."""
    reach = 0.85
    return Layout(center=(0.55 * reach, 0.0), spread=0.18 * reach, size=0.02, table_half=(0.5 * reach + 0.35, 0.7 * reach + 0.1),
                  table_center=(0.5 * reach - 0.1, 0.0), bimanual=False, reach=reach)


def yaw_quat(yaw: float) -> list[float]:
    """wxyz quaternion of a rotation about world z."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
