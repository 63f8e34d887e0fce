"""Offscreen camera rendering tuned for dataset export.

Export renders every recorded state from one or more cameras, so the renderer
must be fast on a CPU (Mesa llvmpipe) as well as on a GPU. MuJoCo's defaults
(shadow maps, 4x MSAA, a 640x480 buffer, floor reflections, an infinite floor
drawn as a 200x200 quad grid, capsules of 28x16 facets, textures blending two
mipmap levels) cost ~40x over what a small training image needs.
`tune_model` turns those off on a *copy* of the model, never on the one the
caller simulates with, and `FastRenderer` drives MuJoCo's low-level mjr API
with one reused GL context, scene and readback buffer.
"""

from __future__ import annotations

import copy
import os
import subprocess
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from scenes.errors import TeleopError, first_line

BACKENDS = ("egl", "osmesa", "glfw")
_chosen_backend: str | None = None


class RenderError(TeleopError, RuntimeError):
    """No usable OpenGL backend, or a camera that is not in the model; one line."""


@dataclass(frozen=True)
class RenderSettings:
    """What `tune_model` changes; every field off means MuJoCo's look, at MuJoCo's cost."""

    no_shadows: bool = True
    no_multisampling: bool = True
    no_reflections: bool = True  # a reflective floor renders the scene twice
    finite_planes: bool = True  # infinite planes are drawn as 40k quads
    size_buffer: bool = True  # offscreen buffer = image size, not the model's (often 640x480)
    fit_tessellation: bool = True  # spheres, capsules, cylinders with as many facets as the image shows
    one_mip_level: bool = True  # 2D textures sample the nearest mipmap level, not a blend of two


TUNED = RenderSettings()
DEFAULTS = RenderSettings(False, False, False, False, False, False, False)  # MuJoCo's own settings, for comparison


def tune_model(model: mujoco.MjModel, width: int, height: int, settings: RenderSettings = TUNED) -> mujoco.MjModel:
    """A copy of `model` set up for fast offscreen rendering at width x height."""
    m = copy.copy(model)
    if settings.size_buffer:
        m.vis.global_.offwidth, m.vis.global_.offheight = int(width), int(height)
    else:  # keep the model's buffer, grown if the image needs more
        m.vis.global_.offwidth = max(int(width), int(m.vis.global_.offwidth))
        m.vis.global_.offheight = max(int(height), int(m.vis.global_.offheight))
    if settings.no_shadows:
        m.vis.quality.shadowsize = 0
        m.light_castshadow[:] = 0
    if settings.no_multisampling:
        m.vis.quality.offsamples = 0
    if settings.no_reflections:
        m.mat_reflectance[:] = 0
    if settings.finite_planes:
        _finite_planes(m)
    if settings.fit_tessellation:
        _fit_tessellation(m, max(int(width), int(height)))
    return m


def _fit_tessellation(m: mujoco.MjModel, pixels: int) -> None:
    """Fewer facets on round primitives for small images (never more than the model asks for).

    MuJoCo draws a capsule with 28 slices x 16 stacks whatever the image size; at 224
    pixels a robot link spans up to about a hundred pixels in the cameras framed on
    the work (scenes.assembly.arena), and 19 x 11 gives the same picture but for a few edge
    pixels, in less rendering time on a CPU (14 x 8 showed facets on the arm as it
    reached under `overhead`). Facets grow with the image: 28 slices again from 336
    pixels up; at 144 pixels and less, 12. Boxes and planes keep their subdivision
    (`numquads`): lighting is interpolated across it, which shows.
    """
    q = m.vis.quality
    slices = min(int(q.numslices), max(12, round(pixels / 12)))
    stacks = min(int(q.numstacks), max(6, round(q.numstacks * slices / max(1, q.numslices))))
    q.numslices, q.numstacks = slices, stacks


def _finite_planes(m: mujoco.MjModel) -> None:
    """Give infinite planes a finite size and a coarse grid, keeping their texture scale.

    An infinite plane's texture repeats every 2/texrepeat metres; a finite plane's
    every 2*size/texrepeat unless its material is texuniform, so the material is
    switched to texuniform, but only when planes alone use it.
    """
    half = float(min(m.vis.map.zfar, 10.0) * m.stat.extent)
    planes = [g for g in range(m.ngeom) if m.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    for g in planes:
        if m.geom_size[g, 0] > 0 and m.geom_size[g, 1] > 0:
            continue
        mat = int(m.geom_matid[g])
        if mat >= 0 and m.mat_texuniform[mat] == 0:
            users = {int(x) for x in np.flatnonzero(m.geom_matid == mat)}
            if not users <= set(planes):
                continue  # shared with a box or mesh: leave this plane infinite
            m.mat_texuniform[mat] = 1
        for k in (0, 1):
            if m.geom_size[g, k] <= 0:
                m.geom_size[g, k] = half
        m.geom_size[g, 2] = max(float(m.geom_size[g, 2]), half / 15.0)  # ~30x30 quads


def _sample_one_mip_level(con: mujoco.MjrContext) -> None:
    """2D textures filtered with GL_LINEAR_MIPMAP_NEAREST instead of MuJoCo's GL_LINEAR_MIPMAP_LINEAR.

    Trilinear filtering reads 8 texels a pixel from two mipmap levels and blends them;
    on a CPU renderer (Mesa llvmpipe) that is ~15% of a 224x224 frame of the textured
    floor. Bilinear filtering of the nearest level moves a few pixels by 1-2 levels of
    255. Best effort: the picture is right either way, so a GL error leaves MuJoCo's filter.
    """
    try:
        from OpenGL import GL

        for i in range(con.ntexture):
            if int(con.textureType[i]) == mujoco.mjtTexture.mjTEXTURE_2D:  # skyboxes (cube maps) keep theirs
                GL.glBindTexture(GL.GL_TEXTURE_2D, int(con.texture[i]))
                GL.glTexParameteri(GL.GL_TEXTURE_2D, GL.GL_TEXTURE_MIN_FILTER, GL.GL_LINEAR_MIPMAP_NEAREST)
        GL.glBindTexture(GL.GL_TEXTURE_2D, 0)
    except Exception:  # noqa: BLE001 - PyOpenGL raises GLError, NullFunctionError, ImportError
        pass


_probes: dict[str, subprocess.Popen] = {}
_current = threading.local()  # the FastRenderer whose GL context is current in this thread


def _start_probe(backend: str) -> None:
    """Check in a child whether `backend` makes a context (a failed GL import poisons a process)."""
    if backend in _probes:
        return
    code = f"from mujoco.{backend} import GLContext; c = GLContext(8, 8); c.make_current(); c.free()"
    env = {**os.environ, "MUJOCO_GL": backend}
    env.pop("PYOPENGL_PLATFORM", None)
    try:
        _probes[backend] = subprocess.Popen(
            [sys.executable, "-c", code], env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )
    except OSError:
        pass


def _probe(backend: str) -> bool:
    _start_probe(backend)
    proc = _probes.get(backend)
    if proc is None:
        return False
    try:
        return proc.wait(timeout=60) == 0
    except subprocess.TimeoutExpired:
        proc.kill()
        return False


def warm_up() -> None:
    """Start choosing the GL backend now, in the background (it takes a Python start-up)."""
    if _chosen_backend is None and not os.environ.get("MUJOCO_GL", "").strip():
        _start_probe("egl")


def gl_backend() -> str:
    """The OpenGL backend to render with: MUJOCO_GL if set, else EGL, else OSMesa."""
    global _chosen_backend
    if _chosen_backend is not None:
        return _chosen_backend
    wanted = os.environ.get("MUJOCO_GL", "").strip().lower()
    if wanted:
        if wanted not in BACKENDS:
            raise RenderError(f"MUJOCO_GL={wanted!r} cannot render offscreen here (use one of: {', '.join(BACKENDS)})")
        _chosen_backend = wanted
        return wanted
    for backend in ("egl", "osmesa"):
        if _probe(backend):
            _chosen_backend = backend
            return backend
    raise RenderError(
        "no OpenGL backend for offscreen rendering: install EGL or OSMesa "
        "(Debian: apt-get install libegl1 libgl1-mesa-dri libosmesa6) or set MUJOCO_GL"
    )


def rasterize_in_render_threads() -> None:
    """Have Mesa's CPU renderer (llvmpipe) rasterize in the thread that renders (LP_NUM_THREADS=0) unless the
    environment says otherwise: for work that renders each camera in a thread of its own (`teleop video`, the
    review page) llvmpipe's own rasterizer threads only add handoffs. Measured for front + wrist at 320x240 with
    the encoder: 8.1-8.3 ms of CPU a frame against 8.8-10.0. It takes effect only before the process's first GL
    context (Mesa reads it once); GPU drivers ignore it."""
    os.environ.setdefault("LP_NUM_THREADS", "0")


def _gl_context(backend: str, width: int, height: int):
    try:
        if backend == "egl":
            from mujoco.egl import GLContext
        elif backend == "osmesa":
            from mujoco.osmesa import GLContext
        else:
            from mujoco.glfw import GLContext
        ctx = GLContext(width, height)
        ctx.make_current()
    except Exception as exc:  # noqa: BLE001 - GL stacks raise anything from ImportError to GLError
        first = first_line(exc)
        raise RenderError(f"cannot create an OpenGL context with MUJOCO_GL={backend}: {first}") from None
    return ctx


class FastRenderer:
    """Renders RGB images of named cameras from an MjData, one GL context for all of them.

    The model given is not modified: rendering uses a tuned copy (see `tune_model`).
    Pose data comes from the caller's MjData (same model layout), so replaying
    with the original model and rendering with the copy is fine.
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        width: int,
        height: int,
        cameras: list[str],
        settings: RenderSettings = TUNED,
        backend: str | None = None,
    ):
        if width <= 0 or height <= 0:
            raise RenderError(f"image size must be positive, got {width}x{height}")
        self.width, self.height = int(width), int(height)
        self.cameras = list(cameras)
        self.settings = settings
        self.backend = backend or gl_backend()
        self._con = None
        self._ctx = _gl_context(self.backend, self.width, self.height)
        self._option = mujoco.MjvOption()
        self._perturb = mujoco.MjvPerturb()
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._rect = mujoco.MjrRect(0, 0, self.width, self.height)
        self._buf = np.empty((self.height, self.width, 3), dtype=np.uint8)
        self.load(model)

    def load(self, model: mujoco.MjModel) -> None:
        """Render another model (e.g. the next episode's: seeds move objects) in the same GL context."""
        camera_ids = []
        for name in self.cameras:
            cid = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_CAMERA, name)
            if cid < 0:
                have = [model.camera(i).name for i in range(model.ncam)]
                raise RenderError(f"no camera {name!r} in the model (cameras: {', '.join(have) or 'none'})")
            camera_ids.append(cid)
        self.camera_ids = camera_ids
        self.model = tune_model(model, self.width, self.height, self.settings)
        self._ctx.make_current()
        _current.renderer = self
        if self._con is not None:
            self._con.free()
        self._con = mujoco.MjrContext(self.model, mujoco.mjtFontScale.mjFONTSCALE_100)
        mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
        if self._con.currentBuffer != mujoco.mjtFramebuffer.mjFB_OFFSCREEN:
            raise RenderError("the OpenGL context has no offscreen framebuffer")
        if self.settings.one_mip_level:
            _sample_one_mip_level(self._con)
        self._scene = mujoco.MjvScene(self.model, maxgeom=max(1000, 2 * self.model.ngeom))

    def reload(self, model: mujoco.MjModel, cameras: Sequence[str]) -> None:
        """Render `cameras` of `model` from now on, the GL context made current in the calling thread (reused:
        ~3 ms, against 0.1-0.2 s for a fresh context on a CPU renderer; see replay.render_pool)."""
        self.cameras = list(cameras)
        self.load(model)

    def release(self) -> None:
        """Let go of the GL context in the calling thread (EGL), so that another thread can make it current."""
        if getattr(_current, "renderer", None) is self:
            _current.renderer = None
        if self.backend == "egl":
            from mujoco import egl

            egl.EGL.eglMakeCurrent(egl.EGL_DISPLAY, egl.EGL.EGL_NO_SURFACE, egl.EGL.EGL_NO_SURFACE, egl.EGL.EGL_NO_CONTEXT)

    def render(self, data: mujoco.MjData, camera: int | str = 0, channel_first: bool = False) -> np.ndarray:
        """A new (H, W, 3) uint8 image, top row first, of camera index or name at `data`'s poses.

        `data` must be forward-computed (mj_forward, or at least kinematics and
        mj_camlight: camera and light poses live in MjData). With `channel_first`
        the image is (3, H, W), each channel contiguous (what the export feeds LeRobot).
        """
        if getattr(_current, "renderer", None) is not self:  # another renderer's context may be current
            self._ctx.make_current()
            _current.renderer = self
        index = self.cameras.index(camera) if isinstance(camera, str) else camera
        self._camera.fixedcamid = self.camera_ids[index]
        mujoco.mjv_updateScene(
            self.model, data, self._option, self._perturb, self._camera, mujoco.mjtCatBit.mjCAT_ALL, self._scene
        )
        mujoco.mjr_render(self._rect, self._scene, self._con)
        mujoco.mjr_readPixels(self._buf, None, self._rect, self._con)
        image = self._buf[::-1]  # GL rows run bottom-up; callers keep frames, so copy
        return np.ascontiguousarray(image.transpose(2, 0, 1)) if channel_first else image.copy()

    def render_all(self, data: mujoco.MjData, channel_first: bool = False) -> list[np.ndarray]:
        """One image per camera, in the order given at construction."""
        return [self.render(data, i, channel_first) for i in range(len(self.camera_ids))]

    def close(self) -> None:
        if getattr(_current, "renderer", None) is self:
            _current.renderer = None
        con, self._con = getattr(self, "_con", None), None
        if con is not None:
            self._ctx.make_current()  # free this context's GL objects, not another's
            con.free()
        ctx, self._ctx = getattr(self, "_ctx", None), None
        if ctx is not None:
            try:
                ctx.free()
            except Exception:  # noqa: BLE001 - freeing at shutdown must not raise
                pass

    def __enter__(self) -> FastRenderer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
