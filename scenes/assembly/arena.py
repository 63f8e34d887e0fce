"""The room every task shares: floor, table, lights and the fixed cameras.

Everything is sized from the robot's reach so that a 0.35 m SO-101 and a
0.85 m Panda both get a table they can work on and cameras that frame it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mujoco
import numpy as np

from scenes.cameras.view import CameraPose, fit_points

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
    The fixed cameras frame the layout's placement spread; `frame_cameras` frames
    them on a task's own work area once its objects are in.
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


FRONT_SIDE = 180.0  # deg, azimuth of the side `front` stands on: behind the robot (at the origin, facing +x)
FRONT_AZIMUTH = -45.0  # deg off that side, to the robot's left: over its shoulder, past the arm, seeing what it faces
FRONT_ELEVATION = 45.0  # deg above the table of `front`'s line of sight (robosuite's agentview: ~35-45)
FRONT_FOVY = 25.0  # deg: a narrow lens from farther away keeps far objects nearly as large as near ones
BIMANUAL_FRONT = -60.0  # deg, azimuth of a bimanual pair's `front`: the front side (-y) between the arms, a little to the right
OVERHEAD_SIDE = -90.0  # deg, azimuth `overhead` leans in from: the robot's right
OVERHEAD_TILT = 30.0  # deg from straight down: objects show a side, the arm above the work hides less
OVERHEAD_FOVY = 20.0  # deg: from higher up the arm over the work looms less
VIEW_MARGIN = 0.05  # share of the half-image left free around the work area
MIN_VIEW = 0.35  # reaches: the work area shown is at least this wide, so the gripper's approach stays in the picture
WORK_HEIGHT = 0.3  # reaches above the table over the work area's middle that `front` keeps in view (the gripper's approach)


def layout_work_points(layout: Layout) -> np.ndarray:
    """The layout's own work area (N x 3, m, world): the spread box grown by a cube, up to two cube sizes high."""
    cx, cy = layout.center
    s, r = layout.spread + layout.size * math.sqrt(2), layout.size
    return np.array([[cx + x, cy + y, TABLE_TOP + z] for x in (-s, s) for y in (-s, s) for z in (0.0, 2 * r)], float)


def _widened(points: np.ndarray, layout: Layout) -> np.ndarray:
    """`points` plus, where the work area is narrower than MIN_VIEW reaches, corners that widen it about its centre."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    want = MIN_VIEW * (layout.reach or 0.85) / 2  # half-width, m
    hx, hy = max(half[0], want), max(half[1], want)
    extra = np.array([[mid[0] + sx * hx, mid[1] + sy * hy, TABLE_TOP] for sx in (-1, 1) for sy in (-1, 1)], float)
    return np.concatenate([points, extra])


def _above(points: np.ndarray, layout: Layout) -> np.ndarray:
    """Points WORK_HEIGHT reaches over the table along the work area's middle line in x (where the gripper comes in)."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    z = TABLE_TOP + WORK_HEIGHT * (layout.reach or 0.85)
    return np.array([[x, (lo[1] + hi[1]) / 2, z] for x in (lo[0], hi[0])], float)


def _axes(forward: np.ndarray, up_hint: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(right, up) of a camera looking along `forward` whose image up leans towards `up_hint`."""
    f = forward / np.linalg.norm(forward)
    up = up_hint - float(np.dot(up_hint, f)) * f
    up /= np.linalg.norm(up)
    return np.cross(f, up), up


def framed_cameras(layout: Layout, work: np.ndarray | None = None) -> dict[str, CameraPose]:
    """`front` and `overhead`, each the closest camera of its direction that keeps `work` (N x 3, m, world) in view.

    front: agentview-like over the robot's shoulder: from behind and to the left of
    a single arm (FRONT_SIDE + FRONT_AZIMUTH), so the faces of what it works on (a
    door, a drawer) are seen as the arm sees them, looking down FRONT_ELEVATION
    degrees; a bimanual pair is seen from the side, between the arms. It also keeps
    WORK_HEIGHT reaches above the work in view, where the gripper comes in.
    overhead: from high above, OVERHEAD_TILT off straight down leaning in from the
    robot's right (a bimanual pair: from the front side), the robot at the bottom.
    """
    points = _widened(layout_work_points(layout) if work is None else np.asarray(work, float), layout)
    az = math.radians(BIMANUAL_FRONT if layout.bimanual else FRONT_SIDE + FRONT_AZIMUTH)  # where `front` stands
    el = math.radians(FRONT_ELEVATION)
    front_dir = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    right, up = _axes(front_dir, np.array([0.0, 0.0, 1.0]))
    tilt = math.radians(OVERHEAD_TILT)
    side = -math.pi / 2 if layout.bimanual else math.radians(OVERHEAD_SIDE)
    over_dir = -np.array([math.sin(tilt) * math.cos(side), math.sin(tilt) * math.sin(side), math.cos(tilt)])
    over_up = np.array([0.0, 1.0, 0.0]) if layout.bimanual else np.array([1.0, 0.0, 0.0])
    o_right, o_up = _axes(over_dir, over_up)
    return {
        "front": fit_points(np.concatenate([points, _above(points, layout)]), right, up, FRONT_FOVY, VIEW_MARGIN),
        "overhead": fit_points(points, o_right, o_up, OVERHEAD_FOVY, VIEW_MARGIN),
    }


def room_camera(layout: Layout) -> CameraPose:
    """`room`: the wide view of the robot and the whole table, for people watching (the `front` camera of earlier scenes)."""
    cx, cy = layout.center
    dist = max(0.6, 2.2 * layout.spread + 0.45)
    if layout.bimanual:
        target = np.array([cx, cy, TABLE_TOP + 0.1])
        eye = np.array([cx, cy - 1.5 * dist, TABLE_TOP + 0.9 * dist])
    else:
        target = np.array([0.6 * cx, cy, TABLE_TOP + 0.35 * cx])
        eye = np.array([cx + 1.5 * dist, cy + 0.6 * dist, TABLE_TOP + 0.9 * dist])
    return CameraPose(pos=tuple(map(float, eye)), xyaxes=tuple(look_at_xyaxes(eye, target)), fovy=50.0)


def _add_cameras(world: mujoco.MjsBody, layout: Layout) -> None:
    """`front` and `overhead` framed on the layout's spread, then `room` (the wide view)."""
    for name, pose in framed_cameras(layout).items():
        pose.add_to(world, name)
    room_camera(layout).add_to(world, "room")


def frame_cameras(spec: mujoco.MjSpec, layout: Layout, work: np.ndarray | None) -> None:
    """Point `front` and `overhead` of an arena spec at `work` (N x 3 world points, m; None: the layout's spread)."""
    for name, pose in framed_cameras(layout, work).items():
        cam = spec.camera(name)
        cam.pos = list(pose.pos)
        cam.alt.type = mujoco.mjtOrientation.mjORIENTATION_XYAXES
        cam.alt.xyaxes = list(pose.xyaxes)
        cam.fovy = pose.fovy


def reference_layout() -> Layout:
    """The layout of a 0.85 m reach arm with 0.02 m cubes (Panda): task files are checked against it."""
    reach = 0.85
    return Layout(center=(0.55 * reach, 0.0), spread=0.18 * reach, size=0.02, table_half=(0.5 * reach + 0.35, 0.7 * reach + 0.1),
                  table_center=(0.5 * reach - 0.1, 0.0), bimanual=False, reach=reach)


def yaw_quat(yaw: float) -> list[float]:
    """wxyz quaternion of a rotation about world z."""
    return [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
