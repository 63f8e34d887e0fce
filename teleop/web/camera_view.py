"""A live picture from one of the scene's cameras, rendered offscreen a few times a second.

MuJoCo picks its GL backend when it is first imported, from MUJOCO_GL. On a
machine without a display the default (GLFW) cannot open a context, so
`choose_gl_backend` sets EGL or OSMesa before the import when the user has not
chosen. If no backend works the panel says so, and the session runs on.

The renderer has its own model copy (no shadows, no multisampling, an
offscreen buffer the size of the image: several times faster in software GL)
and its own MjData filled from snapshots; the GL context lives in this thread.
"""

from __future__ import annotations

import copy
import ctypes.util
import os
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

IMAGE_SIZE = (192, 144)  # width, height
FRAME_HZ = 4.0
_GL_PROBLEM: str | None = None  # set once GL failed in this process: a second try can hang (GLFW)


def choose_gl_backend() -> str:
    """Set MUJOCO_GL for offscreen rendering unless the user chose; returns the backend name."""
    chosen = os.environ.get("MUJOCO_GL", "").strip().lower()
    if chosen:
        return chosen
    if not sys.platform.startswith("linux"):
        return "default"
    if ctypes.util.find_library("EGL"):
        os.environ["MUJOCO_GL"] = "egl"
    elif ctypes.util.find_library("OSMesa"):
        os.environ["MUJOCO_GL"] = "osmesa"
    else:
        return "glfw"
    if "mujoco" in sys.modules:  # too late for this process: MuJoCo read MUJOCO_GL at import
        return "default"
    return os.environ["MUJOCO_GL"]


def gl_help() -> str:
    return (
        "set MUJOCO_GL=egl (Debian: libegl1, libgl1-mesa-dri) or MUJOCO_GL=osmesa (libosmesa6) "
        "before starting teleop"
    )


class CameraFeed:
    """Renders `camera()` from the latest snapshot into `show(image)` at `hz`."""

    def __init__(
        self,
        get_snapshot: Callable[[], object],
        camera: Callable[[], str],
        show: Callable[[np.ndarray], None],
        fail: Callable[[str], None],
        wanted: Callable[[], bool] = lambda: True,
        size: tuple[int, int] = IMAGE_SIZE,
        hz: float = FRAME_HZ,
    ) -> None:
        self.get_snapshot = get_snapshot
        self.camera = camera
        self.show = show
        self.fail = fail
        self.wanted = wanted
        self.size = size
        self.period = 1.0 / hz
        self.frames = 0
        self.problem: str | None = None
        self.ready = threading.Event()  # set once the renderer exists (or failed)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="teleop-camera", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(3.0)

    def _model_for(self, model):
        import mujoco

        model = copy.copy(model)
        model.vis.quality.shadowsize = 0
        model.vis.quality.offsamples = 0
        model.vis.global_.offwidth = max(self.size[0], 1)
        model.vis.global_.offheight = max(self.size[1], 1)
        return model, mujoco.MjData(model)

    def _open(self, snap):
        """Model copy, MjData and renderer for `snap`'s model; None (after `fail`) if GL is not there."""
        import mujoco

        global _GL_PROBLEM
        model, data = self._model_for(snap.model)
        if _GL_PROBLEM is None:
            try:
                renderer = mujoco.Renderer(model, self.size[1], self.size[0])
            except Exception as exc:  # noqa: BLE001 - any GL failure means "no pictures", not a crash
                reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
                backend = os.environ.get("MUJOCO_GL", "default")
                _GL_PROBLEM = f"camera images are off: no OpenGL context (MUJOCO_GL={backend}: {reason}); {gl_help()}"
        if _GL_PROBLEM is not None:
            self.problem = _GL_PROBLEM
            self.fail(self.problem)
            return None
        return model, data, renderer

    def _run(self) -> None:
        import mujoco

        snap = self.get_snapshot()
        opened = self._open(snap)
        self.ready.set()
        if opened is None:
            return
        model, data, renderer = opened
        generation = snap.generation
        try:
            while not self._stop.is_set():
                started = time.perf_counter()
                snap = self.get_snapshot()
                if self.wanted():
                    if snap.generation != generation:  # a reset compiled a new model
                        renderer.close()
                        opened = self._open(snap)
                        if opened is None:
                            return
                        model, data, renderer = opened
                        generation = snap.generation
                    data.qpos[:] = snap.qpos
                    if model.nmocap:
                        data.mocap_pos[:] = snap.mocap_pos
                        data.mocap_quat[:] = snap.mocap_quat
                    mujoco.mj_kinematics(model, data)
                    mujoco.mj_comPos(model, data)
                    mujoco.mj_camlight(model, data)
                    try:
                        renderer.update_scene(data, camera=self.camera())
                    except (KeyError, ValueError):
                        renderer.update_scene(data)
                    self.show(renderer.render().copy())
                    self.frames += 1
                self._stop.wait(max(0.0, self.period - (time.perf_counter() - started)))
        finally:
            try:
                renderer.close()
            except Exception:  # noqa: BLE001 - closing a context at exit
                pass
