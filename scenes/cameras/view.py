"""What a fixed camera sees: framing a set of world points, and how many pixels an object covers.

Frames follow MuJoCo's camera convention: a camera looks along its frame's -z with
x to the right and y up, `fovy` is the vertical field of view in degrees, and pixels
are square, so the focal length in pixels is (H / 2) / tan(fovy / 2) on both axes.
Lengths are metres in the world frame; image coordinates are pixels, u to the right
and v down from the top-left corner.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import mujoco
import numpy as np

FIGURE_SIZE = 96  # px: the image side the object-pixel figure is given at (object_px_at_96)


@dataclass(frozen=True)
class CameraPose:
    """A fixed camera as MJCF writes it: position (m, world), xyaxes (right then up, world) and fovy (deg)."""

    pos: tuple[float, float, float]
    xyaxes: tuple[float, float, float, float, float, float]
    fovy: float

    def add_to(self, body: mujoco.MjsBody, name: str) -> None:
        """Add this camera to a spec body (the world body for a fixed camera)."""
        body.add_camera(name=name, pos=list(self.pos), xyaxes=list(self.xyaxes), fovy=float(self.fovy))


def look_at_axes(eye: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(right, up, forward) unit vectors of a camera at `eye` looking at `target` with world z up."""
    forward = np.asarray(target, float) - np.asarray(eye, float)
    norm = float(np.linalg.norm(forward))
    if norm < 1e-9:
        raise ValueError("a camera cannot look at its own position")
    forward = forward / norm
    right = np.cross(forward, [0.0, 0.0, 1.0])
    if np.linalg.norm(right) < 1e-6:  # looking straight up or down: image right is world -y
        right = np.array([0.0, -1.0, 0.0])
    right /= np.linalg.norm(right)
    return right, np.cross(right, forward), forward


def fit_points(points: np.ndarray, right: np.ndarray, up: np.ndarray, fovy: float, margin: float = 0.05) -> CameraPose:
    """The closest camera with axes (right, up) that keeps every point (N x 3, m) inside a square image.

    With the orientation fixed, "point inside the view cone" is linear in the eye
    position: |x| <= t * depth and |y| <= t * depth in camera coordinates, with
    t = tan(fovy / 2) * (1 - margin). Moving the eye as far forward as those allow has
    a closed form: per axis, the two tightest tangent planes meet in a line, the
    nearer of the two lines bounds the depth; across the image the eye is then put
    where the points' projection is centred. `margin` is the share of the
    half-image left free at the tightest side.
    """
    pts = np.asarray(points, float).reshape(-1, 3)
    right = np.asarray(right, float) / np.linalg.norm(right)
    up = np.asarray(up, float) / np.linalg.norm(up)
    forward = np.cross(up, right)  # camera looks along -z = right x up
    t = math.tan(math.radians(fovy) / 2) * (1.0 - margin)
    px, py, pz = pts @ right, pts @ up, pts @ forward
    a, b = float(np.max(px - t * pz)), float(np.min(px + t * pz))
    c, d = float(np.max(py - t * pz)), float(np.min(py + t * pz))
    ez = min(b - a, d - c) / (2 * t)
    depth = pz - ez
    eye = _centred(px, depth) * right + _centred(py, depth) * up + ez * forward
    return CameraPose(pos=tuple(float(v) for v in eye), xyaxes=(*map(float, right), *map(float, up)), fovy=float(fovy))


def _centred(p: np.ndarray, depth: np.ndarray) -> float:
    """The eye coordinate e along one image axis that centres the points' projection: max((p - e) / depth)
    = -min((p - e) / depth). That sum falls as e grows, so bisection between min(p) and max(p) finds it."""
    lo, hi = float(p.min()), float(p.max())
    for _ in range(60):
        mid = (lo + hi) / 2
        q = (p - mid) / depth
        lo, hi = (mid, hi) if float(q.max() + q.min()) > 0 else (lo, mid)
    return (lo + hi) / 2


def _camera_frame(model: mujoco.MjModel, data: mujoco.MjData, camera: int) -> tuple[np.ndarray, np.ndarray, float]:
    """(position, rotation with columns right/up/backward, fovy deg) of a camera after mj_forward."""
    return data.cam_xpos[camera].copy(), data.cam_xmat[camera].reshape(3, 3).copy(), float(model.cam_fovy[camera])


def project(model: mujoco.MjModel, data: mujoco.MjData, camera: int, points: np.ndarray,
            width: int = FIGURE_SIZE, height: int = FIGURE_SIZE) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N x 2: u right, v down) of world points (N x 3, m), and whether each is in front of the camera."""
    pos, rot, fovy = _camera_frame(model, data, camera)
    local = (np.asarray(points, float).reshape(-1, 3) - pos) @ rot  # camera frame: x right, y up, z backward
    depth = -local[:, 2]
    ahead = depth > 1e-9
    safe = np.where(ahead, depth, 1.0)
    focal = (height / 2) / math.tan(math.radians(fovy) / 2)
    uv = np.stack([width / 2 + focal * local[:, 0] / safe, height / 2 - focal * local[:, 1] / safe], axis=1)
    return uv, ahead


def body_geoms(model: mujoco.MjModel, body: int) -> list[int]:
    """The visible geoms (groups 0-2, not transparent) of a body and every body below it."""
    below = {body}
    for b in range(body + 1, model.nbody):  # MuJoCo numbers a body after its parent
        if int(model.body_parentid[b]) in below:
            below.add(b)
    return [g for g in range(model.ngeom)
            if int(model.geom_bodyid[g]) in below and int(model.geom_group[g]) < 3 and float(model.geom_rgba[g, 3]) > 0]


def geom_corners(model: mujoco.MjModel, data: mujoco.MjData, geoms: Iterable[int]) -> np.ndarray:
    """World corners (8 per geom, m) of the geoms' bounding boxes (MuJoCo's geom_aabb, in each geom's frame)."""
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    out = []
    for g in geoms:
        center, half = model.geom_aabb[g, :3], model.geom_aabb[g, 3:]
        local = center + signs * half
        out.append(data.geom_xpos[g] + local @ data.geom_xmat[g].reshape(3, 3).T)
    return np.concatenate(out) if out else np.zeros((0, 3))


def width_px(model: mujoco.MjModel, data: mujoco.MjData, camera: int, corners: np.ndarray,
             width: int = FIGURE_SIZE, height: int = FIGURE_SIZE) -> float:
    """How many pixels across (image u) a set of corners spans, clipped to the image; 0 when any is behind the camera."""
    if len(corners) == 0:
        return 0.0
    uv, ahead = project(model, data, camera, corners, width, height)
    if not ahead.all():
        return 0.0
    u = np.clip(uv[:, 0], 0.0, width)
    v = np.clip(uv[:, 1], 0.0, height)
    if float(v.max() - v.min()) <= 0.0:
        return 0.0  # wholly above or below the image
    return float(u.max() - u.min())


def object_px(model: mujoco.MjModel, data: mujoco.MjData, camera: int | str, bodies: Iterable[int],
              size: int = FIGURE_SIZE) -> float:
    """The smallest projected width (px, at size x size) among the given object bodies, at `data`'s poses.

    Each object is bounded by its visible geoms' boxes (its subtree's), so the width
    is a little over the silhouette for round or rotated shapes; occlusion is ignored.
    `data` must be forward-computed (camera and geom poses live in MjData).
    """
    cam = camera if isinstance(camera, int) else model.camera(camera).id
    widths = [width_px(model, data, cam, geom_corners(model, data, body_geoms(model, b)), size, size) for b in bodies]
    return min(widths) if widths else 0.0


def in_view(model: mujoco.MjModel, data: mujoco.MjData, camera: int | str, points: np.ndarray, size: int = FIGURE_SIZE) -> bool:
    """Whether every world point (N x 3, m) projects inside the size x size image."""
    cam = camera if isinstance(camera, int) else model.camera(camera).id
    uv, ahead = project(model, data, cam, points, size, size)
    return bool(ahead.all() and (uv >= -1e-6).all() and (uv <= size + 1e-6).all())
