"""A live picture from one of the scene's cameras, rendered offscreen a few times a second.

Rendering goes through `replay.render.FastRenderer` (the exporter's renderer:
a tuned model copy, one GL context reused across resets, the GL backend
probed in a child process), fed from snapshots into this thread's own MjData,
so the physics is never touched. Creating the GL context holds the GIL for
about 0.1 s, so the web app opens the renderer before the control loop
starts. If no backend works the panel says so, and the session runs on.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from scenes.errors import first_line
from teleop.web.shared.cpu_pressure import cpu_pressure
from teleop.web.shared.loop_thread import LoopThread

IMAGE_SIZE = (192, 144)  # width, height
FRAME_HZ = 4.0
STILL_EPS = 1e-4  # m (and quaternion units): bodies that moved less than this since the last picture change no pixel
# When the machine's CPUs are crowded (teleop.web.shared.cpu_pressure: some task waited for a CPU this share of the last
# ~10 s), the picture comes at BUSY_HZ: the control loop and the 3D view need the cores more than a thumbnail does.
BUSY_PRESSURE = 50.0  # %
BUSY_HZ = 1.0
_GL_PROBLEM: str | None = None  # set once GL failed in this process: a second try can hang (GLFW)


def warm_up() -> None:
    """Start probing the GL backend in the background (it costs a Python start-up)."""
    from replay.render import warm_up as start_probe

    start_probe()


class CameraFeed(LoopThread):
    """Renders `camera()` from the latest snapshot into `show(image)` at `hz`, or `busy_hz` while `pressure()` (CPU
    pressure, percent) is at least `busy_pressure`; `notice(text)` says so, in plain text ("" once it is over)."""

    join_timeout = 3.0

    def __init__(
        self,
        get_snapshot: Callable[[], object],
        cameras: tuple[str, ...],
        camera: Callable[[], str],
        show: Callable[[np.ndarray], None],
        fail: Callable[[str], None],
        wanted: Callable[[], bool] = lambda: True,
        size: tuple[int, int] = IMAGE_SIZE,
        hz: float = FRAME_HZ,
        pressure: Callable[[], float | None] = cpu_pressure,
        busy_pressure: float = BUSY_PRESSURE,
        busy_hz: float = BUSY_HZ,
        notice: Callable[[str], None] = lambda text: None,
    ) -> None:
        self.get_snapshot = get_snapshot
        self.cameras = list(cameras)
        self.camera = camera
        self.show = show
        self.fail = fail
        self.wanted = wanted
        self.size = size
        self.period = 1.0 / hz
        self.pressure = pressure
        self.busy_pressure = busy_pressure
        self.busy_period = max(self.period, 1.0 / busy_hz)
        self.notice = notice
        self.crowded = False  # the picture is at busy_hz now
        self.frames = 0
        self.still = 0  # pictures not rendered: nothing had moved since the one shown
        self.problem: str | None = None
        self.ready = threading.Event()  # set once the renderer exists (or failed)
        self._init_thread("teleop-camera")

    def _open(self, model):
        """A renderer for `model`'s cameras; None (after `fail`) if there is no GL here."""
        global _GL_PROBLEM
        from replay.render import FastRenderer, RenderError

        if _GL_PROBLEM is None:
            try:
                return FastRenderer(model, self.size[0], self.size[1], self.cameras)
            except RenderError as exc:
                _GL_PROBLEM = f"camera images are off: {exc}"
            except Exception as exc:  # noqa: BLE001 - any GL failure means "no pictures", not a crash
                first = first_line(exc)
                _GL_PROBLEM = (f"camera images are off: no OpenGL context ({first}); set MUJOCO_GL=egl "
                               "(Debian: libegl1 libgl1-mesa-dri) or MUJOCO_GL=osmesa (libosmesa6)")
        self.problem = _GL_PROBLEM
        self.fail(self.problem)
        return None

    def _run(self) -> None:
        import mujoco

        snap = self.get_snapshot()
        renderer = self._open(snap.model)
        self.ready.set()
        if renderer is None:
            return
        data = mujoco.MjData(snap.model)
        generation = snap.generation
        shown: tuple | None = None  # (generation, camera, body poses) of the picture on the page
        try:
            while not self._stop.is_set():
                started = time.perf_counter()
                snap = self.get_snapshot()
                period = self.period
                if self.wanted():
                    if self._crowded():
                        period = self.busy_period
                    if snap.generation != generation:  # a reset compiled a new model: same context, new model
                        renderer.load(snap.model)
                        data = mujoco.MjData(snap.model)
                        generation = snap.generation
                    name = self.camera()
                    poses = np.concatenate((snap.xpos.ravel(), snap.xquat.ravel()))
                    if self._still(shown, generation, name, poses):  # an idle operator's page keeps its picture
                        self.still += 1
                    else:
                        snap.pose(data)
                        mujoco.mj_comPos(snap.model, data)
                        mujoco.mj_camlight(snap.model, data)
                        self.show(renderer.render(data, name if name in self.cameras else 0))
                        self.frames += 1
                        shown = (generation, name, poses)
                else:
                    shown = None  # no page: the next one gets a picture at once
                self._stop.wait(max(0.0, period - (time.perf_counter() - started)))
        except Exception as exc:  # noqa: BLE001 - the picture stops, the session goes on
            self.problem = f"camera images stopped: {type(exc).__name__}: {exc}"
            self.fail(self.problem)
        finally:
            renderer.close()

    def _crowded(self) -> bool:
        """Whether the CPUs are crowded now; tells the page when that changes."""
        pressure = self.pressure()
        crowded = pressure is not None and pressure >= self.busy_pressure
        if crowded != self.crowded:
            self.crowded = crowded
            every = f"{self.busy_period:g} s"
            self.notice(f"one picture every {every} while this machine's CPUs are busy (CPU pressure "
                        f"{self.busy_pressure:g} % or more)" if crowded else "")
        return crowded

    @staticmethod
    def _still(shown: tuple | None, generation: int, camera: str, poses: np.ndarray) -> bool:
        """Whether the picture shown is still what the camera sees: same model (so the same bodies), same camera,
        no body moved."""
        if shown is None or shown[0] != generation or shown[1] != camera:
            return False
        return bool(np.max(np.abs(poses - shown[2])) < STILL_EPS)
