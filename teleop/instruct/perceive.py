"""Object positions from one rendered RGB-D view, never from the simulator's object state.

Each object of the task file is found by its colour (the file's `rgba`): a pixel belongs to the
object whose colour it is a shade of (the colour scaled by the lighting, within a tolerance that
grows with the colour's saturation). The object's pixels are back-projected through the depth
image and the camera's intrinsics (MuJoCo's `fovy`, principal point at the image centre) and
extrinsics (the camera's world pose) into world points (m). From them:

- the top surface's height: the highest points (robust percentile);
- the position: the middle of the top surface's extent in x, y (a rim seen in part too); z halfway between the top and the table
  (a primitive body's origin is its centre), or the table itself for a bin or a mesh (their origin is their base);
- the yaw (rad, about world z) of a box from its top surface's minimum-area rectangle (a
  square's yaw is known mod pi/2, a bar's mod pi; the script engine grasps mod pi anyway).

What the camera cannot see is reported, not guessed: `unseen` (no pixel of the colour),
`cut` (the object touches the image border: partly out of view), `occluded` (something
nearer the camera borders much of its outline: the arm in front of it). A translucent object
(a target mark) is looked for on the table's surface only.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import mujoco
import numpy as np
from scipy import ndimage

from replay.render import RenderError, gl_backend, tune_model
from scenes.assembly.arena import TABLE_TOP

OCCLUDED_FRACTION = 0.2  # of an object's outline bordered by something nearer the camera: occluded
NEARER_M = 0.01  # a neighbour pixel this much nearer the camera than the object's edge is in front of it
MIN_PIXELS = 6  # fewer pixels of a colour than this is noise, not an object


@dataclass(frozen=True)
class SceneObject:
    """What the task file says an object looks like: its name, shape word and colour (rgba, 0..1)."""

    name: str
    shape: str
    rgba: tuple[float, float, float, float]
    fixed: bool = False


def scene_objects(task) -> list[SceneObject]:
    """The task file's objects (a task without a file has none the camera can look for)."""
    out = []
    for obj in getattr(task, "objects", ()):
        default = (0.55, 0.57, 0.6, 1.0) if obj.shape in ("bin", "mjcf") else (0.85, 0.2, 0.15, 1.0)
        rgba = tuple(float(v) for v in obj.raw.get("rgba", default))
        rgba = rgba + (1.0,) * (4 - len(rgba))
        out.append(SceneObject(obj.name, obj.shape, rgba[:4], bool(obj.raw.get("fixed", False))))
    return out


@dataclass
class Estimate:
    """One object as the camera saw it (world frame, m and rad); position None when unseen."""

    name: str
    status: str  # "visible" | "occluded" | "cut" | "unseen"
    position: np.ndarray | None = None
    top_z: float | None = None
    yaw: float | None = None  # boxes only
    half_extent: float | None = None  # m, half the top surface's larger side (how far to stand off to push it)
    pixels: int = 0
    occluded_fraction: float = 0.0
    box: tuple[int, int, int, int] | None = None  # (row0, col0, row1, col1) in the image, for drawing

    @property
    def visible(self) -> bool:
        return self.status == "visible"


@dataclass
class Perception:
    """Every object's estimate from one view, the view itself and what it took."""

    camera: str
    width: int
    height: int
    estimates: dict[str, Estimate]
    rgb: np.ndarray = field(repr=False)
    depth: np.ndarray = field(repr=False)
    ms: float = 0.0  # estimating every object from the view (rendering excluded)


class RgbdCamera:
    """Renders RGB and metric depth (m along the optical axis) of a model's named cameras offscreen."""

    def __init__(self, model: mujoco.MjModel, width: int = 224, height: int = 224) -> None:
        if width <= 0 or height <= 0:
            raise RenderError(f"image size must be positive, got {width}x{height}")
        backend = gl_backend()
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        else:
            from mujoco.glfw import GLContext
        self.width, self.height = int(width), int(height)
        self._ctx = GLContext(self.width, self.height)
        self._ctx.make_current()
        self._con = None
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self.load(model)

    def load(self, model: mujoco.MjModel) -> None:
        """Render `model` from now on (the next episode's scene)."""
        self.model = tune_model(model, self.width, self.height)
        self._ctx.make_current()
        if self._con is not None:
            self._con.free()
        self._con = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        self._scene = mujoco.MjvScene(self.model, maxgeom=max(1000, 2 * self.model.ngeom))

    def camera_id(self, camera: str) -> int:
        cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        if cid < 0:
            have = [self.model.camera(i).name for i in range(self.model.ncam)]
            raise RenderError(f"no camera {camera!r} in the scene (cameras: {', '.join(have) or 'none'})")
        return cid

    def capture(self, data: mujoco.MjData, camera: str) -> tuple[np.ndarray, np.ndarray]:
        """(H, W, 3) uint8 RGB and (H, W) float depth in metres, top row first, at `data`'s poses."""
        self._ctx.make_current()
        self._camera.fixedcamid = self.camera_id(camera)
        mujoco.mjv_updateScene(self.model, data, self._option, self._perturb, self._camera, mujoco.mjtCatBit.mjCAT_ALL,
                               self._scene)
        mujoco.mjr_render(self._rect, self._scene, self._con)
        rgb = np.empty((self.height, self.width, 3), dtype=np.uint8)
        depth = np.empty((self.height, self.width), dtype=np.float32)
        mujoco.mjr_readPixels(rgb, depth, self._rect, self._con)
        extent = self.model.stat.extent
        near, far = self.model.vis.map.znear * extent, self.model.vis.map.zfar * extent
        metres = near / (1.0 - depth.astype(np.float64) * (1.0 - near / far))  # the depth buffer is nonlinear in distance
        return rgb[::-1].copy(), metres[::-1].copy()

    def close(self) -> None:
        if self._con is not None:
            self._ctx.make_current()
            self._con.free()
            self._con = None
        try:
            self._ctx.free()
        except Exception:  # noqa: BLE001 - freeing at shutdown must not raise
            pass


def back_project(depth: np.ndarray, model: mujoco.MjModel, data: mujoco.MjData, camera_id: int) -> np.ndarray:
    """(H, W, 3) world points (m) of a depth image: pinhole intrinsics from the camera's fovy, then its world pose."""
    h, w = depth.shape
    f = 0.5 * h / math.tan(math.radians(float(model.cam_fovy[camera_id])) / 2)
    u = (np.arange(w) + 0.5 - w / 2) / f
    v = (np.arange(h) + 0.5 - h / 2) / f
    cam = np.empty((h, w, 3))
    cam[..., 0] = u[None, :] * depth
    cam[..., 1] = -v[:, None] * depth
    cam[..., 2] = -depth  # MuJoCo's cameras look along their -z, y up
    rot = data.cam_xmat[camera_id].reshape(3, 3)
    return cam @ rot.T + data.cam_xpos[camera_id]


def colour_residual(rgb: np.ndarray, colour: np.ndarray, power: np.ndarray | None = None) -> np.ndarray:
    """How far each pixel is from being a shade of `colour` (0: exactly; relative to the pixel's brightness).

    The part of the pixel's RGB vector off the colour's direction, over the pixel's length; `power`
    (the pixels' squared lengths) may be passed in when several colours are tried on one image.
    """
    c = np.asarray(colour, rgb.dtype)
    power = np.einsum("...k,...k->...", rgb, rgb) if power is None else power
    along = rgb @ c
    off = np.maximum(power - along * along / float(c @ c), 0.0)
    return np.sqrt(off / np.maximum(power, 1.0))


def tolerance(colour: np.ndarray) -> float:
    """The residual a shade of `colour` may have: tight for greys (the arm is grey too), looser for vivid colours."""
    c = np.asarray(colour, float)
    saturation = float(np.linalg.norm(c - c.mean()) / max(np.linalg.norm(c), 1e-9))
    return float(np.clip(0.3 * saturation, 0.02, 0.1))


def perceive_view(
    rgb: np.ndarray, depth: np.ndarray, points: np.ndarray, objects: list[SceneObject], camera: str
) -> Perception:
    """Every object's estimate from an RGB image, its depth (m) and world points (m)."""
    t0 = time.perf_counter()
    image = rgb.astype(np.float32)
    power = np.einsum("...k,...k->...", image, image)
    z = points[..., 2]
    colours = {obj.name: np.array(obj.rgba[:3]) for obj in objects}  # a translucent mark renders near its own colour
    names = [o.name for o in objects]
    residuals = np.stack([colour_residual(image, colours[n], power) for n in names]) if names else np.zeros((0,) + z.shape)
    above = z > TABLE_TOP - 0.004  # the floor around the table is no object
    bright = image.max(axis=-1) > 25
    estimates: dict[str, Estimate] = {}
    taken: dict[tuple, int] = {}  # objects of one colour share its blobs, largest first
    for i, obj in enumerate(objects):
        key = tuple(np.round(colours[obj.name], 3))
        translucent = obj.rgba[3] < 0.95
        nearest = residuals[i] <= residuals.min(axis=0) + 1e-12  # this object's colour is the pixel's nearest (ties: one colour)
        mask = (residuals[i] < tolerance(colours[obj.name])) & nearest & above & bright
        if translucent:
            mask &= np.abs(z - TABLE_TOP) < 0.01
        labels, n = ndimage.label(mask)
        if n == 0:
            estimates[obj.name] = Estimate(obj.name, "unseen")
            continue
        sizes = ndimage.sum_labels(mask, labels, index=np.arange(1, n + 1))
        order = np.argsort(-sizes)
        rank = taken.get(key, 0)
        taken[key] = rank + 1
        if rank >= n or sizes[order[rank]] < MIN_PIXELS:
            estimates[obj.name] = Estimate(obj.name, "unseen")
            continue
        blob = labels == order[rank] + 1
        estimates[obj.name] = estimate_blob(obj, blob, depth, points)
    return Perception(camera, rgb.shape[1], rgb.shape[0], estimates, rgb, depth, ms=(time.perf_counter() - t0) * 1000)


def estimate_blob(obj: SceneObject, blob: np.ndarray, depth: np.ndarray, points: np.ndarray) -> Estimate:
    """Position, top height, yaw and visibility of one object from its pixels."""
    pts = points[blob]
    top = float(np.percentile(pts[:, 2], 95))
    tol = max(0.004, 0.15 * (top - TABLE_TOP))
    top_pts = pts[pts[:, 2] > top - tol]
    xy = (top_pts[:, :2].min(axis=0) + top_pts[:, :2].max(axis=0)) / 2  # the top's middle: a rim seen in part too
    if obj.shape in ("bin", "mesh"):
        zc = TABLE_TOP  # a bin's and a mesh's origin is at its base
    elif obj.rgba[3] < 0.95 or top - TABLE_TOP < 0.004:
        zc = TABLE_TOP + 0.001  # a flat mark on the table
    else:
        zc = (top + TABLE_TOP) / 2
    yaw, half = rectangle(top_pts[:, :2])
    rows, cols = np.nonzero(blob)
    box = (int(rows.min()), int(cols.min()), int(rows.max()), int(cols.max()))
    h, w = blob.shape
    window = (slice(max(box[0] - 2, 0), box[2] + 3), slice(max(box[1] - 2, 0), box[3] + 3))  # the blob and its outline
    inside, near = blob[window], depth[window]
    ring = ndimage.binary_dilation(inside) & ~inside
    edge_depth = ndimage.minimum_filter(np.where(inside, near, np.inf), size=3)
    nearer = ring & (near < edge_depth - NEARER_M)
    fraction = float(nearer.sum()) / max(int(ring.sum()), 1)
    cut = box[0] == 0 or box[1] == 0 or box[2] == h - 1 or box[3] == w - 1
    status = "cut" if cut else "occluded" if fraction > OCCLUDED_FRACTION else "visible"
    return Estimate(
        obj.name, status, np.array([xy[0], xy[1], zc]), top, yaw if obj.shape == "box" else None, half,
        int(blob.sum()), round(fraction, 3), box,
    )


def rectangle(xy: np.ndarray) -> tuple[float, float]:
    """(yaw in [-pi/2, pi/2) of the longer side, half the longer side) of the smallest rectangle around points (m)."""
    if len(xy) < 3:
        return 0.0, 0.0
    c = xy - xy.mean(axis=0)
    angles = np.radians(np.arange(0.0, 90.0, 1.0))
    cos, sin = np.cos(angles)[:, None], np.sin(angles)[:, None]
    u = c[:, 0] * cos + c[:, 1] * sin  # (angles, points): the points along each candidate's axes
    v = -c[:, 0] * sin + c[:, 1] * cos
    ex, ey = np.ptp(u, axis=1), np.ptp(v, axis=1)
    k = int(np.argmin(ex * ey))
    a, ex, ey = float(angles[k]), float(ex[k]), float(ey[k])
    yaw = a if ex >= ey else a + math.pi / 2
    yaw = (yaw + math.pi / 2) % math.pi - math.pi / 2
    return yaw, max(ex, ey) / 2


def perceive(camera_obj: RgbdCamera, model: mujoco.MjModel, data: mujoco.MjData, objects: list[SceneObject],
             camera: str = "front") -> Perception:
    """Render `camera` at `data`'s poses (a copy, forward-computed: the session's data is not touched) and find the objects."""
    view = mujoco.MjData(model)
    mujoco.mj_copyData(view, model, data)
    mujoco.mj_forward(model, view)
    rgb, depth = camera_obj.capture(view, camera)
    points = back_project(depth, model, view, camera_obj.camera_id(camera))
    return perceive_view(rgb, depth, points, objects, camera)


def draw(perception: Perception) -> np.ndarray:
    """The view with each object's box drawn (green: visible, orange: occluded or cut) and a cross at its centroid."""
    out = perception.rgb.copy()
    for est in perception.estimates.values():
        if est.box is None:
            continue
        r0, c0, r1, c1 = est.box
        colour = (40, 220, 60) if est.visible else (255, 150, 0)
        out[r0, c0:c1 + 1] = out[r1, c0:c1 + 1] = colour
        out[r0:r1 + 1, c0] = out[r0:r1 + 1, c1] = colour
    return out
