"""`teleop video`: an episode's frames rendered from its recorded states, with the overlay strip.

Each control step's recorded state is restored (mj_setState, then kinematics and
camera poses: nothing is re-simulated, so the video is exactly what was recorded)
and rendered from each chosen camera at `size`; the cameras sit side by side and
the strip (replay.review.overlay) goes under them. Each camera renders in a thread
of its own, ahead of the encoder (MuJoCo and the encoder release the GIL, so on two
cores they overlap). Several episodes play one after another, or with `grid`
tile one video, the shorter ones held on their last frame.
"""

from __future__ import annotations

import math
import queue
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from replay.engine import replay_states
from replay.episode import CONTROL_POLICY, Episode, EpisodeError, find_episodes, load_episode
from replay.features import CameraChoiceError, resolve_cameras
from replay.handoff import put_unless
from replay.judge import judge_steps
from replay.render_pool import RENDERERS
from replay.review.encode import VideoError, VideoWriter, check_writable, video_format
from replay.review.overlay import STRIP_HEIGHT, Overlay, StepInfo, Timeline
from replay.review.timebase import control_dt
from replay.subtasks.sidecar import AnnotationError, read_subtasks

DEFAULT_SIZE = (320, 240)  # each camera's width x height, px
AHEAD = 32  # frames rendered ahead of the encoder


@dataclass(frozen=True)
class VideoOptions:
    """What `teleop video` was asked for."""

    cameras: tuple[str, ...] = ()  # empty: front and the wrist cameras the episode has, else its first camera
    size: tuple[int, int] = DEFAULT_SIZE
    fps: float | None = None  # None: the first episode's control rate (real time)
    grid: bool = False
    overlay: bool = True


def parse_size(text: str) -> tuple[int, int]:
    """'320x240' -> (320, 240); anything else is a VideoError."""
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise VideoError(f"--size {text}: expected WIDTHxHEIGHT, e.g. 320x240") from None
    if not (8 <= w <= 4096 and 8 <= h <= 4096):
        raise VideoError(f"--size {text}: each side must be 8..4096 pixels")
    return w, h


def model_cameras(model: mujoco.MjModel) -> list[str]:
    return [model.camera(i).name for i in range(model.ncam)]


def choose_cameras(episode: Episode, model: mujoco.MjModel, asked: Sequence[str]) -> list[str]:
    """The cameras to render, as the export chooses them (replay.features.resolve_cameras: `wrist` is
    every arm's wrist camera); none asked: front and the wrist cameras it has, else its first camera."""
    have = model_cameras(model)
    try:
        chosen = resolve_cameras(list(asked) if asked else None, have)
    except CameraChoiceError as exc:
        raise VideoError(f"{episode.path}: {exc}") from None
    chosen = chosen or have[:1]
    if not chosen:
        raise VideoError(f"{episode.path}: the episode's model has no camera")
    return chosen


def driver_labels(episode: Episode) -> list[str]:
    """Who drove each step: the operator (and the devices), a policy, a generator or a script."""
    meta = episode.meta
    devices = ", ".join(d.split(":")[0] for d in meta.devices)
    name = getattr(meta, "operator", None) or meta.extra.get("operator")  # a campaign's episodes name their operator
    operator = str(name or "operator") + (f" ({devices})" if devices else "")
    if meta.source == "generated":
        base = "generated"
    elif meta.source == "policy":
        base = f"policy {Path(meta.policy).name}" if meta.policy else "policy"
    elif meta.source == "script":
        base = "script"
    else:
        base = operator
    if episode.control is None:
        return [base] * episode.steps
    policy = f"policy {Path(meta.policy).name}" if meta.policy else "policy"
    return [policy if c == CONTROL_POLICY else operator for c in episode.control]


def subtask_spans(episode: Episode) -> list[tuple[str, int, int]]:
    """(object, start, end) of the episode's stored subtasks; none when it has none (or they do not fit)."""
    try:
        found = read_subtasks(episode.path, episode.steps)
    except AnnotationError:
        return []
    return [(s.object, s.start, s.end) for s in found or []]


def step_infos(episode: Episode, success: np.ndarray | None = None) -> tuple[Timeline, list[StepInfo]]:
    """The overlay's timeline and one StepInfo per control step."""
    dt = control_dt(episode)
    spans = subtask_spans(episode)
    timeline = Timeline(episode.meta.task or episode.meta.scene, episode.steps, episode.seconds, spans)
    if success is None:
        success = judge_steps(episode)
    drivers = driver_labels(episode)
    current = np.full(episode.steps, -1)
    for i, (_, start, end) in enumerate(spans):
        current[start:end] = i
    infos = [StepInfo(k, k * dt, int(current[k]) if current[k] >= 0 else None, drivers[k], bool(success[k]))
             for k in range(episode.steps)]
    return timeline, infos


class EpisodeFrames:
    """An episode's composed frames (cameras side by side, the strip under them), each camera rendered in a thread."""

    def __init__(self, episode: Episode, cameras: Sequence[str], size: tuple[int, int], overlay: bool = True) -> None:
        if episode.steps == 0:
            raise VideoError(f"{episode.path}: the episode has no steps")
        self.episode = episode
        self.model = episode.build_model()
        self.cameras = choose_cameras(episode, self.model, cameras)
        self.size = size
        self.width = size[0] * len(self.cameras)
        self.height = size[1] + (STRIP_HEIGHT if overlay else 0)
        self.overlay = None
        if overlay:
            timeline, self.infos = step_infos(episode)
            self.overlay = Overlay(timeline, self.width)

    def __len__(self) -> int:
        return self.episode.steps

    def _camera(self, index: int, out: queue.Queue, stop: threading.Event) -> None:
        """Render one camera at every recorded state into `out`, in a GL context lent to this thread (kept warm
        across videos: replay.render_pool)."""
        try:
            with RENDERERS.renderer(self.model, *self.size, [self.cameras[index]]) as renderer:
                for _, data in replay_states(self.episode, self.model, kinematics_only=True):
                    mujoco.mj_camlight(self.model, data)
                    if not put_unless(out, renderer.render(data, 0), stop):
                        return
        except BaseException as exc:  # noqa: BLE001 - raised again in the reading thread
            put_unless(out, exc, stop)

    def __iter__(self) -> Iterator[np.ndarray]:
        """The frames in order. Each camera renders in a thread of its own (two cameras in one thread take
        turns on a CPU renderer); their images are put side by side with the strip under them here, in the
        reading thread, as the encoder takes them: a thread more for that only added waits for the GIL."""
        sources = [queue.Queue(maxsize=AHEAD) for _ in self.cameras]
        stop = threading.Event()
        workers = [threading.Thread(target=self._camera, args=(c, q, stop), name=f"video-camera-{c}", daemon=True)
                   for c, q in enumerate(sources)]
        for worker in workers:
            worker.start()
        try:
            w, h = self.size
            for k in range(self.episode.steps):
                frame = np.empty((self.height, self.width, 3), np.uint8)
                for c, source in enumerate(sources):
                    image = source.get()
                    if isinstance(image, BaseException):
                        raise image
                    frame[:h, c * w:(c + 1) * w] = image
                if self.overlay is not None:
                    frame[h:] = self.overlay.strip(self.infos[k])
                yield frame
        finally:
            stop.set()  # the camera threads end (they are done, or the reader has gone)
            for worker in workers:
                worker.join()


def tile(frames: Sequence[np.ndarray], cols: int) -> np.ndarray:
    """Frames of one size in a grid `cols` wide, row by row; empty cells black."""
    h, w = frames[0].shape[:2]
    rows = math.ceil(len(frames) / cols)
    out = np.zeros((rows * h, cols * w, 3), np.uint8)
    for i, f in enumerate(frames):
        r, c = divmod(i, cols)
        out[r * h:(r + 1) * h, c * w:(c + 1) * w] = f
    return out


def load_all(paths: Sequence[str | Path]) -> list[Episode]:
    """Every episode named (folders expanded); none at all is a VideoError."""
    try:
        files = find_episodes(paths)
        if not files:
            raise VideoError(f"no episode files in {', '.join(str(p) for p in paths)}")
        return [load_episode(f) for f in files]
    except EpisodeError as exc:
        raise VideoError(str(exc)) from None


def write_video(paths: Sequence[str | Path], out: str | Path, options: VideoOptions = VideoOptions()) -> dict:
    """Render and encode the episodes at `paths` into `out` (.mp4 or .gif); what was written, as a dict."""
    out = check_writable(out)
    episodes = load_all(paths)
    return write_episodes(episodes, out, options)


def write_episodes(episodes: Sequence[Episode], out: str | Path, options: VideoOptions = VideoOptions()) -> dict:
    """`write_video` for episodes already loaded."""
    out = check_writable(out)
    try:
        sources = [EpisodeFrames(ep, options.cameras, options.size, options.overlay) for ep in episodes]
    except EpisodeError as exc:
        raise VideoError(str(exc)) from None
    if len({(s.width, s.height) for s in sources}) > 1:
        raise VideoError("the episodes' frames differ in size (name the same --camera for all)")
    fps = options.fps or episodes[0].meta.control_hz or 1.0 / control_dt(episodes[0])
    writer = VideoWriter(out, fps)
    t0 = time.perf_counter()
    try:
        if options.grid and len(sources) > 1:
            cols = math.ceil(math.sqrt(len(sources)))
            iters = [iter(s) for s in sources]
            last: list[np.ndarray | None] = [None] * len(sources)
            for _ in range(max(len(s) for s in sources)):
                for i, it in enumerate(iters):
                    last[i] = next(it, last[i])
                writer.write(tile(last, cols))  # type: ignore[arg-type]
        else:
            for source in sources:
                for frame in source:
                    writer.write(frame)
        writer.close()
    except BaseException:
        writer.abort()
        raise
    wall = time.perf_counter() - t0
    return {
        "out": str(out), "format": video_format(out), "frames": writer.frames, "fps": float(writer.fps),
        "width": writer.width, "height": writer.height,
        "episodes": [str(ep.path) for ep in episodes], "cameras": sources[0].cameras,
        "grid": bool(options.grid and len(sources) > 1), "overlay": options.overlay,
        "wall_seconds": round(wall, 3), "frames_per_s": round(writer.frames / wall, 1) if wall > 0 else None,
    }
