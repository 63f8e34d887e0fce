"""FastRenderers whose GL contexts outlive one use, for work that renders episode after episode.

On Mesa's llvmpipe a fresh GL context costs 0.1-0.2 s of CPU before its first image
(the driver's start, MjrContext's first texture upload, whose mipmaps compile a blit,
and the first draw's shaders), while loading the next model into a context already
used costs ~3 ms. A 5 s episode's video renders in about that much time again, so the
review page (a video on each episode's first view, a thumbnail per row) and `teleop
video` over a folder keep their contexts: `RENDERERS.renderer(...)` lends an idle one
of the same size, made current in the calling thread and loaded with the new model and
cameras, and takes it back afterwards.

Only EGL contexts are lent: an EGL context can be made current in another thread once
the thread that used it has let it go (eglMakeCurrent with no context). With OSMesa or
GLFW every use gets a fresh renderer, as before.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager

import mujoco

from replay.render import TUNED, FastRenderer, RenderSettings, gl_backend

KEEP = 4  # idle renderers kept per process (a video's cameras, a thumbnail)


class RendererPool:
    """Idle FastRenderers by (width, height, settings), lent one at a time."""

    def __init__(self, keep: int = KEEP) -> None:
        self.keep = keep
        self._idle: list[FastRenderer] = []
        self._lock = threading.Lock()
        self.created = 0  # renderers made (a GL context each)
        self.lent = 0  # uses served

    def _take(self, width: int, height: int, settings: RenderSettings) -> FastRenderer | None:
        with self._lock:
            for i, r in enumerate(self._idle):
                if (r.width, r.height, r.settings) == (width, height, settings):
                    return self._idle.pop(i)
        return None

    def _give_back(self, renderer: FastRenderer) -> None:
        renderer.release()
        with self._lock:
            if len(self._idle) < self.keep:
                self._idle.append(renderer)
                return
        renderer.close()

    @contextmanager
    def renderer(self, model: mujoco.MjModel, width: int, height: int, cameras: Sequence[str],
                 settings: RenderSettings = TUNED) -> Iterator[FastRenderer]:
        """A FastRenderer of `model`'s `cameras` at width x height, current in this thread while the block runs."""
        pooled = gl_backend() == "egl"
        renderer = self._take(int(width), int(height), settings) if pooled else None
        if renderer is None:
            renderer = FastRenderer(model, width, height, list(cameras), settings)
            with self._lock:
                self.created += 1
        else:
            try:
                renderer.reload(model, cameras)
            except BaseException:
                renderer.close()
                raise
        with self._lock:
            self.lent += 1
        try:
            yield renderer
        except BaseException:
            renderer.close()  # a renderer that failed mid-use is not lent again
            raise
        if pooled:
            self._give_back(renderer)
        else:
            renderer.close()

    def clear(self) -> None:
        """Close every idle renderer (their GL contexts)."""
        with self._lock:
            idle, self._idle = self._idle, []
        for r in idle:
            r.close()


RENDERERS = RendererPool()
