"""The export's frames, replayed and rendered in a thread of their own, ahead of LeRobot.

Each frame is replayed (mj_setState + mj_forward), its features built and its
cameras rendered; LeRobot then takes it (`add_frame`) and at each episode's end
writes the episode (`save_episode`: ~2 ms a frame of Python in HF datasets).
Replay and rendering spend most of their time in MuJoCo and OpenGL, which
release the GIL, so in a thread they overlap LeRobot's main-thread work and its
encoder threads instead of taking turns with them: on a 2-core machine the
export is then bounded by the CPU time it needs, not by one thread's latency.
Frames come out in recorded order, at most `ahead` frames ahead of the consumer.

An OpenGL context belongs to the thread that makes it current, so the renderer
is made, used and freed in the stream's thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import mujoco

from replay.engine import replay_states
from replay.episode import Episode
from replay.export_frames import INTERVENTION, FrameBuilder, intervention_values, robot_layout
from replay.render import FastRenderer

QUEUE_BYTES = 64 << 20  # frames waiting for LeRobot, at most (~200 frames of two 224x224 cameras)


@dataclass(frozen=True)
class EpisodeEnd:
    """In the stream after an episode's last frame."""

    index: int  # position in the episodes given to `start`
    steps: int


@dataclass(frozen=True)
class _Job:
    episodes: list[Callable[[], Episode] | None]
    action: str
    task: Callable[[Episode], str]
    keys: list[str]  # dataset key of each camera
    channel_first: list[bool]  # per camera, as the dataset declares it
    intervention: bool = False  # add the per-frame `intervention` feature


_DONE = object()


class FrameStream:
    """Frames (dicts for `add_frame`) and EpisodeEnd markers, produced in a thread.

    Construction makes the renderer in that thread and raises its RenderError here;
    `start` gives the episodes; iterating yields in order and raises what the thread
    raised (e.g. EpisodeError for a file that changed since it was scanned). `close`
    stops the thread and frees the renderer; call it whatever happens.
    """

    def __init__(self, model: mujoco.MjModel, size: tuple[int, int], cameras: Sequence[str]):
        width, height = size
        per_frame = max(1, 3 * width * height * len(cameras))
        self._queue: queue.Queue = queue.Queue(maxsize=max(4, min(256, QUEUE_BYTES // per_frame)))
        self._stop = threading.Event()
        self._started = threading.Event()
        self._ready = threading.Event()
        self._job: _Job | None = None
        self._error: BaseException | None = None
        self.backend = ""
        self._thread = threading.Thread(
            target=self._run, args=(model, size, list(cameras)), name="export-frames", daemon=True
        )
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            error, self._error = self._error, None
            raise error

    def start(
        self,
        episodes: Sequence[Callable[[], Episode]],
        action: str,
        task: Callable[[Episode], str],
        keys: Sequence[str],
        channel_first: Sequence[bool],
        intervention: bool = False,
    ) -> None:
        """Begin producing: each callable loads one episode, in export order."""
        self._job = _Job(list(episodes), action, task, list(keys), list(channel_first), intervention)
        self._started.set()

    def __iter__(self) -> Iterator[dict | EpisodeEnd]:
        while True:
            try:  # a timed wait: the main thread returns to Python often enough to act on Ctrl-C
                item = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            if item is _DONE:
                return
            if isinstance(item, BaseException):
                raise item
            yield item

    def close(self) -> None:
        self._stop.set()
        self._started.set()
        self._thread.join()

    # -- the thread -----------------------------------------------------------

    def _put(self, item) -> bool:
        """Queue an item unless the consumer has gone; False: stop producing."""
        while not self._stop.is_set():
            try:
                self._queue.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def _run(self, model: mujoco.MjModel, size: tuple[int, int], cameras: list[str]) -> None:
        renderer = None
        try:
            if cameras:
                renderer = FastRenderer(model, *size, cameras)
                self.backend = renderer.backend
        except BaseException as exc:  # noqa: BLE001 - handed to the constructor's caller
            self._error = exc
        finally:
            self._ready.set()
        if self._error is not None:
            return
        try:
            self._started.wait()
            if self._job is not None and not self._stop.is_set():
                self._produce(self._job, renderer)
        except BaseException as exc:  # noqa: BLE001 - raised again in the consumer's thread
            self._put(exc)
        finally:
            if renderer is not None:
                renderer.close()

    def _produce(self, job: _Job, renderer: FastRenderer | None) -> None:
        for i, load in enumerate(job.episodes):
            job.episodes[i] = None  # let each episode's arrays go once replayed
            ep = load()
            model = ep.build_model()
            if renderer is not None and i > 0:
                renderer.load(model)  # seeds move objects: each episode has its own model
            build = FrameBuilder(robot_layout(ep.meta, model), job.action)
            task = job.task(ep)
            driven = intervention_values(ep.control, ep.meta.source, ep.steps) if job.intervention else None
            for k, data in replay_states(ep, model):
                frame = build(data, ep.ctrl[k], ep.ee_target[k])
                if driven is not None:
                    frame[INTERVENTION] = driven[k]
                if renderer is not None:
                    for c, key in enumerate(job.keys):
                        frame[key] = renderer.render(data, c, job.channel_first[c])
                frame["task"] = task
                if not self._put(frame):
                    return
            if not self._put(EpisodeEnd(i, ep.steps)):
                return
        self._put(_DONE)
