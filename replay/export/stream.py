"""The export's frames, replayed and rendered in a thread of their own, ahead of LeRobot.

Each frame is replayed (mj_setState + mj_forward), its features built and its
cameras rendered; LeRobot then takes it (`add_frame`) and at each episode's end
writes the episode (`save_episode`: ~2 ms a frame of Python in HF datasets).
Replay and rendering spend most of their time in MuJoCo and OpenGL, which
release the GIL, so in a thread they overlap LeRobot's main-thread work and its
encoder threads instead of taking turns with them: on a 2-core machine the
export is then bounded by the CPU time it needs, not by one thread's latency.
Frames come out in recorded order, at most `ahead` frames ahead of the consumer.

With two or more cameras the cameras are split between the stream's thread and a
render worker thread with a GL context of its own, each replaying the episode
itself: rendering (~3.5 ms of MuJoCo and Mesa a camera at 224x224 on a CPU) was
the export's bottleneck, the frame queue ran empty, and two cameras in one
thread took turns. An OpenGL context belongs to the thread that makes it
current, so each renderer is made, used and freed in its own thread.
"""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass

import mujoco
import numpy as np

from replay.engine import replay_states
from replay.episode import Episode
from replay.features import ENV_STATE, INTERVENTION, FrameBuilder, intervention_values, object_layout, robot_layout
from replay.export.review_meta import SUBTASK_INDEX
from replay.handoff import put_unless
from replay.render import FastRenderer
from scenes.cameras.extra import ExtraCamera

QUEUE_BYTES = 64 << 20  # frames waiting for LeRobot, at most (~200 frames of two 224x224 cameras)


@dataclass(frozen=True)
class EpisodeEnd:
    """In the stream after an episode's last frame."""

    index: int  # position in the episodes given to `start`
    steps: int  # frames written
    variation: dict | None = None  # what its `prepare` said of it (replay/export/looks.py), if any
    dropped: int = 0  # idle frames left out (`drop_idle`)


# A frame is idle when its action, robot state and objects' poses are all within this of the last frame
# kept (rad, m, quaternion components, gripper fraction): a pause, a wait for the gripper. A slow motion
# is kept at a lower rate (its frames are kept each time it has moved this far), never dropped whole.
IDLE_TOLERANCE = 1e-3
IDLE_KEYS = ("action", "observation.state", ENV_STATE)


def idle_mask(frames: Sequence[dict]) -> list[bool]:
    """Per frame: keep it (True) or drop it as idle. The first frame is always kept."""
    keep: list[bool] = []
    last: dict | None = None
    for frame in frames:
        if last is not None and all(
            key not in frame or float(np.max(np.abs(frame[key] - last[key]))) <= IDLE_TOLERANCE for key in IDLE_KEYS
        ):
            keep.append(False)
            continue
        keep.append(True)
        last = frame
    return keep


@dataclass(frozen=True)
class _Job:
    episodes: list[Callable[[], Episode] | None]
    action: str
    task: Callable[[Episode], str]
    keys: list[str]  # dataset key of each camera
    channel_first: list[bool]  # per camera, as the dataset declares it
    intervention: bool = False  # add the per-frame `intervention` feature
    objects: bool = False  # add the environment state (the task objects' poses)
    cameras_added: tuple[ExtraCamera, ...] = ()  # put into each recorded model before rendering
    # per episode: (episode, recorded model) -> (the model to render it with, what to record of it); None: as recorded
    prepare: list[Callable[[Episode, mujoco.MjModel], tuple[mujoco.MjModel, dict]]] | None = None
    drop_idle: bool = False  # leave out idle frames (idle_mask)
    subtasks: Callable[[Episode], np.ndarray] | None = None  # each step's `subtask_index` (replay/export/review_meta.py)


_DONE = object()
WORKER_AHEAD = 16  # frames a render worker may run ahead of the stream's thread


class _RenderWorker:
    """Renders some cameras of each episode in a thread of its own, in step with the stream.

    `episode(ep, model, channel_first)` starts one episode; `next()` returns each state's
    images (in `cameras` order) and raises what the thread raised. The model is shared
    read-only; the worker replays into its own MjData.
    """

    def __init__(self, model: mujoco.MjModel, size: tuple[int, int], cameras: list[str], stop: threading.Event):
        self.cameras = cameras
        self._stop = stop
        self._jobs: queue.Queue = queue.Queue()
        self._out: queue.Queue = queue.Queue(maxsize=WORKER_AHEAD)
        self._ready = threading.Event()
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(model, size), name="export-render", daemon=True)
        self._thread.start()
        self._ready.wait()

    def episode(self, ep: Episode, model: mujoco.MjModel, channel_first: list[bool], keep: list[bool] | None = None) -> None:
        """Render this episode's states (those `keep` marks, when given)."""
        self._jobs.put((ep, model, channel_first, keep))

    def next(self) -> list:
        while True:
            try:
                item = self._out.get(timeout=0.1)
            except queue.Empty:
                if self._stop.is_set():
                    raise _Stopped
                continue
            if isinstance(item, BaseException):
                raise item
            return item

    def close(self) -> None:
        self._jobs.put(None)
        self._thread.join()

    def _put(self, item) -> bool:
        return put_unless(self._out, item, self._stop)

    def _run(self, model: mujoco.MjModel, size: tuple[int, int]) -> None:
        try:
            renderer = FastRenderer(model, *size, self.cameras)
        except BaseException as exc:  # noqa: BLE001 - handed to the stream's constructor
            self.error = exc
            self._ready.set()
            return
        self._ready.set()
        try:
            current = model
            while (job := self._jobs.get()) is not None:
                ep, episode_model, channel_first, keep = job
                try:
                    if episode_model is not current:
                        renderer.load(episode_model)
                        current = episode_model
                    for k, data in replay_states(ep, episode_model):
                        if keep is not None and not keep[k]:
                            continue
                        images = [renderer.render(data, c, channel_first[c]) for c in range(len(self.cameras))]
                        if not self._put(images):
                            break
                except BaseException as exc:  # noqa: BLE001 - raised again in the stream's thread
                    self._put(exc)
        finally:
            renderer.close()


class _Stopped(Exception):
    """The consumer went away while the stream's thread waited on a render worker."""


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
        objects: bool = False,
        cameras_added: Sequence[ExtraCamera] = (),
        prepare: Sequence[Callable[[Episode, mujoco.MjModel], tuple[mujoco.MjModel, dict]]] | None = None,
        drop_idle: bool = False,
        subtasks: Callable[[Episode], np.ndarray] | None = None,
    ) -> None:
        """Begin producing: each callable loads one episode, in export order; `cameras_added` go into each one's model;
        `prepare[i]` turns episode i's recorded model into the one it is rendered with (another look);
        `drop_idle` leaves out idle frames (idle_mask), unrendered."""
        self._job = _Job(list(episodes), action, task, list(keys), list(channel_first), intervention, objects, tuple(cameras_added),
                         None if prepare is None else list(prepare), drop_idle, subtasks)
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
        return put_unless(self._queue, item, self._stop)

    def _run(self, model: mujoco.MjModel, size: tuple[int, int], cameras: list[str]) -> None:
        renderer = None
        worker = None
        mine = cameras[: (len(cameras) + 1) // 2] if len(cameras) > 1 else cameras  # the rest go to the worker
        try:
            if cameras:
                renderer = FastRenderer(model, *size, mine)
                self.backend = renderer.backend
            if len(cameras) > 1:
                worker = _RenderWorker(model, size, cameras[len(mine):], self._stop)
                if worker.error is not None:
                    error, worker = worker.error, None
                    raise error
        except BaseException as exc:  # noqa: BLE001 - handed to the constructor's caller
            self._error = exc
        finally:
            self._ready.set()
        try:
            if self._error is not None:
                return
            self._started.wait()
            if self._job is not None and not self._stop.is_set():
                self._produce(self._job, renderer, worker, len(mine))
        except _Stopped:
            pass
        except BaseException as exc:  # noqa: BLE001 - raised again in the consumer's thread
            self._put(exc)
        finally:
            self._stop.set()  # a worker waiting to hand over images stops too
            if worker is not None:
                worker.close()
            if renderer is not None:
                renderer.close()

    def _produce(self, job: _Job, renderer: FastRenderer | None, worker: _RenderWorker | None, own: int) -> None:
        """Replay, features and the first `own` cameras here; the other cameras from the worker, frame by frame."""
        for i, load in enumerate(job.episodes):
            job.episodes[i] = None  # let each episode's arrays go once replayed
            ep = load()
            model = ep.build_model(job.cameras_added)
            variation = None
            if job.prepare is not None:
                model, variation = job.prepare[i](ep, model)
            if renderer is not None and (i > 0 or job.prepare is not None):
                renderer.load(model)  # seeds move objects (and looks change them): each episode has its own model
            arms, objects = robot_layout(ep.meta, model), object_layout(ep.meta, model) if job.objects else None
            keep = None
            if job.drop_idle:  # a first pass without rendering decides which frames are idle
                # (judged with the objects' poses whether or not the dataset holds them: an object still moving is no pause)
                judge = FrameBuilder(arms, job.action, object_layout(ep.meta, model))
                keep = idle_mask([judge(data, ep.ctrl[k], ep.ee_target[k]) for k, data in replay_states(ep, model)])
            if worker is not None:
                worker.episode(ep, model, job.channel_first[own:], keep)
            build = FrameBuilder(arms, job.action, objects)
            task = job.task(ep)
            driven = intervention_values(ep.control, ep.meta.source, ep.steps) if job.intervention else None
            subtask_ids = job.subtasks(ep) if job.subtasks is not None else None
            kept = 0
            for k, data in replay_states(ep, model):
                if keep is not None and not keep[k]:
                    continue
                kept += 1
                frame = build(data, ep.ctrl[k], ep.ee_target[k])
                if driven is not None:
                    frame[INTERVENTION] = driven[k]
                if subtask_ids is not None:
                    frame[SUBTASK_INDEX] = subtask_ids[k:k + 1]
                if renderer is not None:
                    for c in range(own):
                        frame[job.keys[c]] = renderer.render(data, c, job.channel_first[c])
                if worker is not None:
                    for c, image in enumerate(worker.next(), start=own):
                        frame[job.keys[c]] = image
                frame["task"] = task
                if not self._put(frame):
                    return
            if not self._put(EpisodeEnd(i, kept, variation, ep.steps - kept)):
                return
        self._put(_DONE)
