"""The review page's rows: one per episode of a folder, cached beside the episodes.

Scoring an episode replays it (replay.review.quality), so each episode's row is
kept in the folder's cache, `<folder>/.teleop-review/<episode>.row.json`, keyed by
the episode file's size and modification time (and its subtask sidecar's): a
folder is scored once and its list then loads from small files. Verdicts are read
from their sidecars on every listing (they change while reviewing); `long` is
decided over the folder's rows at listing time. Thumbnails and videos are cached
in the same folder, never inside an episode file. A folder that cannot be written
is reviewed all the same, without a cache.
"""

from __future__ import annotations

import json
import os
import struct
import threading
import zlib
from collections.abc import Callable, Sequence
from pathlib import Path

import mujoco
import numpy as np

from replay.episode import Episode, find_episodes, load_episode
from replay.render_pool import RENDERERS
from replay.review.quality import long_outliers, quality, scores
from replay.review.verdicts import read_verdict
from replay.review.video import DEFAULT_SIZE, VideoOptions, choose_cameras, driver_labels, subtask_spans, write_episodes
from replay.subtasks.sidecar import sidecar_path
from scenes.errors import TeleopError, first_line

CACHE_DIR = ".teleop-review"
ROW_VERSION = 2  # raised when the scores change: 2, the jerk at a 30 Hz reference (rows of other rates scored again)
THUMB_SIZE = (96, 72)  # px
_lock = threading.Lock()  # one render at a time: on a 2-core machine two would only take turns
videos_rendered = 0  # review videos rendered by this process (a cached one is not rendered again)


def wait_for_renders(timeout_s: float = 60.0) -> bool:
    """Wait until no thumbnail or video is being rendered (a server stopping waits here: a process that
    exits while another thread holds a GL context may crash in the driver's teardown)."""
    if _lock.acquire(timeout=timeout_s):
        _lock.release()
        return True
    return False


def cache_dir(episode: str | Path) -> Path:
    """The cache folder beside an episode file."""
    return Path(episode).parent / CACHE_DIR


def file_key(episode: str | Path) -> list:
    """What a cached entry was made from: the episode's size and mtime, its subtask sidecar's mtime."""
    st = os.stat(episode)
    try:
        sub = os.stat(sidecar_path(episode)).st_mtime_ns
    except OSError:
        sub = None
    return [ROW_VERSION, st.st_size, st.st_mtime_ns, sub]


def _cache_file(episode: Path, suffix: str) -> Path:
    return cache_dir(episode) / (episode.name + suffix)


def store(path: Path, data: bytes) -> bool:
    """Write a cache file whole (False when the folder cannot be written: the cache is optional)."""
    try:
        path.parent.mkdir(exist_ok=True)
        tmp = path.with_name(f"{path.name}.{os.getpid()}.{threading.get_ident()}.part")
        tmp.write_bytes(data)
        os.replace(tmp, path)
        return True
    except OSError:
        return False


def make_row(episode: Episode) -> dict:
    """An episode's row without its verdict or flags: what it is, who drove it, its quality scores."""
    meta = episode.meta
    return {
        "id": episode.path.name,
        "path": str(episode.path),
        "task": meta.task or meta.scene,
        "scene": meta.scene,
        "robot": meta.robot,
        "source": driver_labels(episode)[0] if episode.steps else meta.source,
        "success": bool(meta.success),
        "duration_s": round(float(episode.seconds), 3),
        "steps": episode.steps,
        "fps": float(meta.control_hz),
        "subtasks": [{"object": o, "start": a, "end": b} for o, a, b in subtask_spans(episode)],
        "scores": scores(episode),
    }


def store_row(path: str | Path, row: dict) -> bool:
    """Cache a row for the episode at `path` as it is now."""
    path = Path(path)
    doc = {"key": file_key(path), "row": row}
    return store(_cache_file(path, ".row.json"), json.dumps(doc).encode())


def cached_row(path: str | Path) -> dict | None:
    """The cached row of an episode, or None when there is none or the file changed since."""
    path = Path(path)
    try:
        doc = json.loads(_cache_file(path, ".row.json").read_bytes())
        if doc.get("key") != file_key(path):
            return None
        return doc["row"]
    except (OSError, ValueError, KeyError, TypeError):
        return None


def episode_row(path: str | Path) -> dict:
    """The row of one episode: cached, or made now (and cached)."""
    path = Path(path)
    row = cached_row(path)
    if row is None:
        row = make_row(load_episode(path))
        store_row(path, row)
    return row


def list_rows(folder: str | Path, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Every episode of `folder` with its verdict and quality (flags and scores), in file-name order.

    An episode that cannot be read is listed with `error` set (and flagged nowhere else).
    """
    paths = find_episodes([folder])
    rows = []
    for i, path in enumerate(paths):
        try:
            row = dict(episode_row(path))
        except Exception as exc:  # noqa: BLE001 - one bad file must not hide the others
            row = {"id": path.name, "path": str(path), "task": "", "source": "", "success": False, "duration_s": 0.0,
                   "steps": 0, "fps": 0.0, "subtasks": [], "scores": {}, "error": str(exc).splitlines()[0]}
        rows.append(row)
        if progress is not None:
            progress(i + 1, len(paths))
    return finish_rows(rows)


def finish_rows(rows: list[dict]) -> list[dict]:
    """Add what changes while reviewing: verdicts (from their sidecars) and flags (`long` over the rows)."""
    long = long_outliers({r["id"]: (r["task"], r["duration_s"]) for r in rows if "error" not in r})
    for row in rows:
        row["quality"] = quality(row.pop("scores", {}), row["id"] in long) if "error" not in row else \
            {"flags": [], "scores": {}}
        row["flags"] = row["quality"]["flags"]
        found = read_verdict(row["path"]) or {}
        row["verdict"] = found.get("verdict")
        row["reviewer"] = found.get("reviewer")
        row["note"] = found.get("note")
        row["reviewed_at"] = found.get("time")
    return rows


def episode_quality(path: str | Path, episode: Episode | None = None, cache: bool = False) -> dict:
    """`{"flags", "scores"}` of one episode; `long` is judged against its folder's scored episodes
    (those `teleop review` has cached). `cache`: keep the row made here (else nothing is written)."""
    path = Path(path)
    row = cached_row(path)
    if row is None:
        row = make_row(episode if episode is not None else load_episode(path))
        if cache:
            store_row(path, row)
    others = {}
    for sibling in find_episodes([path.parent]):
        found = row if sibling == path else cached_row(sibling)
        if found is not None:
            others[sibling.name] = (found["task"], found["duration_s"])
    return quality(row["scores"], path.name in long_outliers(others))


def inspect_quality(episode: Episode) -> dict:
    """`episode_quality` for `teleop inspect`: an episode whose model does not compile (inspect shows
    the rest of it all the same) gets no flags and the reason as `error`."""
    try:
        return episode_quality(episode.path, episode)
    except (TeleopError, ValueError, OSError) as exc:
        return {"flags": [], "scores": {}, "error": first_line(exc)}


def png(image: np.ndarray) -> bytes:
    """An (H, W, 3) uint8 image as PNG bytes (zlib only)."""
    h, w = image.shape[:2]
    raw = b"".join(b"\x00" + image[r].tobytes() for r in range(h))

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body) & 0xFFFFFFFF)

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(raw, 6)) + chunk(b"IEND", b""))


def thumbnail(path: str | Path) -> bytes:
    """A small PNG of the episode's first camera at its middle step (cached)."""
    path = Path(path)
    cache = _cache_file(path, ".thumb.png")
    key = json.dumps(file_key(path)).encode()
    try:
        if cache.with_name(cache.name + ".key").read_bytes() == key:
            return cache.read_bytes()
    except OSError:
        pass
    episode = load_episode(path)
    model = episode.build_model()
    camera = choose_cameras(episode, model, ())[0]
    data = mujoco.MjData(model)
    mujoco.mj_setState(model, data, episode.state[episode.steps // 2], mujoco.mjtState.mjSTATE_INTEGRATION)
    mujoco.mj_forward(model, data)
    with _lock, RENDERERS.renderer(model, *THUMB_SIZE, [camera]) as renderer:
        body = png(renderer.render(data, 0))
    if store(cache, body):
        store(cache.with_name(cache.name + ".key"), key)
    return body


def video(path: str | Path, cameras: Sequence[str] = (), size: tuple[int, int] = DEFAULT_SIZE) -> Path:
    """The episode's review video (rendered on first use and cached beside the episodes)."""
    path = Path(path)
    out = _cache_file(path, ".mp4")
    key = json.dumps([file_key(path), list(cameras), list(size)]).encode()
    keyfile = out.with_name(out.name + ".key")
    if _cached(out, keyfile, key):  # the usual case: no lock to wait on
        return out
    out.parent.mkdir(exist_ok=True)
    with _lock:
        if _cached(out, keyfile, key):  # another request rendered it while this one waited for the lock
            return out
        global videos_rendered
        videos_rendered += 1
        write_episodes([load_episode(path)], out, VideoOptions(cameras=tuple(cameras), size=size))
        store(keyfile, key)
    return out


def _cached(out: Path, keyfile: Path, key: bytes) -> bool:
    """Whether `out` is there and was made from `key` (what its key file says)."""
    try:
        return out.is_file() and keyfile.read_bytes() == key
    except OSError:
        return False
