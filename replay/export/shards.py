"""Export in parallel: shards of episodes exported in worker processes or Ray tasks, merged by LeRobot.

Each shard is a contiguous run of the chosen episodes, exported by the ordinary
single-process export (`export_dataset`) into a dataset of its own under a temporary
directory beside the output. LeRobot's `aggregate_datasets` then joins the shards in
order (parquet data re-indexed, videos joined by stream copy, episode metadata, tasks,
statistics) into the output, so it holds the frames, values and features one process
would have written. Local workers are spawned, never forked: an OpenGL context does not
survive fork. Ray tasks get the episode files as bytes and send their shard back as a tar,
so a cluster needs no shared file system, only this package installed on its nodes.

LeRobot and Ray are optional extras, imported only when an export starts.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import itertools
import multiprocessing
import shutil
import signal
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, replace
from pathlib import Path

from replay.cluster import ClusterError, connect_ray
from replay.errors import first_line
from replay.export.dataset import (
    LEROBOT_HINT,
    ExportError,
    ExportOptions,
    ExportSummary,
    _dir_size,
    _lerobot,
    export_dataset,
    select_episodes,
    video_decoder,
    wants_intervention,
)

# Two shards per worker even out episodes of different lengths, once there are enough episodes for
# that to matter; each shard costs ~1 s more in the merge (LeRobot loads its episode metadata).
SHARDS_PER_WORKER = 2


@dataclass
class _Shard:
    index: int
    files: list[Path]
    frames: int
    out: Path  # the shard's dataset, under the temporary parts directory


def shard_count(episodes: int, parallel: int) -> int:
    """One shard per worker, or two once each of them would still hold a couple of episodes."""
    per_worker = SHARDS_PER_WORKER if episodes >= 2 * SHARDS_PER_WORKER * parallel else 1
    return max(1, min(episodes, parallel * per_worker))


def split(steps: list[int], parts: int) -> list[range]:
    """Contiguous runs of episode indices, in order, none empty, of about equal frames each."""
    n = len(steps)
    parts = max(1, min(parts, n))
    total = sum(steps)
    ends = list(itertools.accumulate(steps))  # frames up to and including episode i
    cuts = [0]
    for k in range(1, parts):
        done = ends[cuts[-1] - 1] if cuts[-1] else 0
        target = done + (total - done) / (parts - k + 1)  # an even share of what is left
        # The cut (an end index) whose frames before it come nearest the target, leaving
        # at least one episode for each shard still to come.
        best = min(range(cuts[-1] + 1, n - (parts - k) + 1), key=lambda i: abs(ends[i - 1] - target))
        cuts.append(best)
    cuts.append(n)
    return [range(a, b) for a, b in zip(cuts, cuts[1:])]


# -- in a worker ------------------------------------------------------------

_progress = None  # a worker's queue back to the driver: (shard index, frames saved so far)
_interruptible = False  # whether Ctrl-C ends a shard here (as it would end the export in the driver)


def _init_worker(progress, interruptible: bool) -> None:
    """Between shards a worker ignores Ctrl-C: one arriving idle would kill it, and with it the pool."""
    global _progress, _interruptible
    _progress, _interruptible = progress, interruptible
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _ready() -> None:
    """Load LeRobot (seconds) before the clock starts, as the single-process export does."""
    _lerobot()


def _export_shard(files: list[Path], opts: ExportOptions, index: int) -> ExportSummary:
    """One shard with the single-process export; after each saved episode the driver's bar moves.

    A Ctrl-C during it ends it as it ends a single-process export: the saved episodes are kept.
    """
    queue = _progress

    def report(episodes: int, frames: int) -> None:
        if queue is not None:
            queue.put((index, frames))

    if _interruptible:
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        return export_dataset(files, replace(opts, on_episode=report), log=lambda line: None)
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)


def _ray_shard(files: list[tuple[str, bytes]], opts: ExportOptions) -> tuple[ExportSummary, bytes]:
    """A shard as a Ray task: episodes in as bytes, the shard's dataset out as a tar (b"" when empty)."""
    with tempfile.TemporaryDirectory(prefix="teleop_export_shard_") as tmp:
        paths = []
        for i, (name, data) in enumerate(files):
            path = Path(tmp) / "episodes" / f"{i:05d}" / name  # one folder each: names may repeat
            path.parent.mkdir(parents=True)
            path.write_bytes(data)
            paths.append(path)
        out = Path(tmp) / "shard"
        summary = export_dataset(paths, replace(opts, out=out), log=lambda line: None)
        return summary, (_tar(out) if out.exists() else b"")


def _tar(directory: Path) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(directory, arcname=".")
    return buffer.getvalue()


def _untar(data: bytes, directory: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(directory, filter="data")


# -- the driver -------------------------------------------------------------


def export_parallel(paths: list, opts: ExportOptions, log: Callable[[str], None]) -> ExportSummary:
    """`export_dataset` with opts.workers > 1 or opts.ray: shards in parallel, then LeRobot's aggregation."""
    if opts.append:
        raise ExportError("appending runs in one process: leave out workers/Ray with append "
                          "(or export to a new directory in parallel)")
    if opts.ray is not None and not opts.ray.strip():
        raise ExportError("Ray address is empty: give auto, HOST:PORT or ray://HOST:PORT")
    chosen, summary = select_episodes(paths, opts, log)
    _check_installed("lerobot", LEROBOT_HINT)  # the full import (seconds) overlaps the workers' start
    if opts.ray is not None:
        ray = _connect_ray(opts.ray)
        parallel = opts.workers if opts.workers > 1 else max(1, int(ray.cluster_resources().get("CPU", 1)))
    else:
        parallel = opts.workers
    runs = split([e.steps for e in chosen], shard_count(len(chosen), parallel))
    # The shards' own settings: what the driver resolved, no progress or callbacks of their own.
    shard_opts = replace(opts, cameras=summary.cameras, only_success=False, progress=False, on_episode=None,
                         workers=1, ray=None, append=False, intervention=wants_intervention(opts, chosen))
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    parts = Path(tempfile.mkdtemp(prefix=opts.out.name + ".parts.", dir=opts.out.parent))
    shards = [_Shard(i, [chosen[k].path for k in run], sum(chosen[k].steps for k in run), parts / f"shard_{i:03d}")
              for i, run in enumerate(runs)]
    bar = _bar(opts, sum(s.frames for s in shards), len(shards), parallel)
    try:
        if opts.ray is not None:
            results, interrupted, t0 = _run_ray(ray, shards, shard_opts, parallel, bar)
        else:
            results, interrupted, t0 = _run_processes(shards, shard_opts, parallel, bar)
        with _no_interrupt():  # a Ctrl-C (a second one) must not cut the merge short
            keep = _prefix(shards, results)
            summary.interrupted = interrupted or len(keep) < len(shards)
            bar.set_description("merging shards")
            _merge(opts, [shards[i] for i, _ in keep])
    finally:
        bar.close()
        shutil.rmtree(parts, ignore_errors=True)
    summary.seconds = time.perf_counter() - t0
    summary.episodes = sum(r.episodes for _, r in keep)
    summary.frames = sum(r.frames for _, r in keep)
    summary.backend = next((r.backend for _, r in keep if r.backend), "")
    if opts.out.exists():
        from lerobot.datasets import LeRobotDatasetMetadata  # optional extra, loaded by the merge already

        summary.dataset_episodes = LeRobotDatasetMetadata(opts.repo_id, root=opts.out).total_episodes
        summary.bytes = _dir_size(opts.out)
    decoder, why = video_decoder()
    if why and opts.video and summary.cameras and summary.episodes:
        log(f"video: {decoder} decoder ({why})")  # as the single-process export says it
    return summary


def _check_installed(module: str, hint: str) -> None:
    """A one-line ExportError naming the extra to install, found without importing the module (seconds)."""
    try:
        found = importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):  # ValueError: blocked in sys.modules (as a test does)
        found = False
    if not found:
        raise ExportError(hint)


def _bar(opts: ExportOptions, frames: int, shards: int, parallel: int):
    """One bar over all shards' frames; it moves as each shard saves an episode."""
    from tqdm import tqdm

    desc = f"{shards} shards on {parallel} workers" if opts.ray is not None else f"starting {parallel} workers"
    return tqdm(total=frames, unit="frame", desc=desc, disable=not opts.progress, file=sys.stderr, dynamic_ncols=True)


def _prefix(shards: list[_Shard], results: list[ExportSummary | None]) -> list[tuple[int, ExportSummary]]:
    """The shards to merge: in order, up to the first one missing or cut short (that one's saved episodes kept)."""
    keep = []
    for shard, result in zip(shards, results):
        if result is None:
            break
        if result.episodes and shard.out.exists():
            keep.append((shard.index, result))
        if result.interrupted or result.episodes < len(shard.files):
            break
    return keep


@contextlib.contextmanager
def _no_interrupt() -> Iterator[None]:
    main = threading.current_thread() is threading.main_thread()
    old = signal.signal(signal.SIGINT, signal.SIG_IGN) if main else None
    try:
        yield
    finally:
        if main:
            signal.signal(signal.SIGINT, old)


def _merge(opts: ExportOptions, shards: list[_Shard]) -> None:
    """LeRobot's aggregation of the shard datasets, in order, into opts.out (nothing when no shard has episodes)."""
    if not shards:
        return
    _lerobot()  # its logging settings, as the shards had them
    from lerobot.datasets.aggregate import aggregate_datasets  # optional extra: pip install '...[lerobot]'

    # aggregate_datasets shows tqdm bars of its own ("Copy data and videos") on stderr: ours is the one bar.
    with contextlib.redirect_stderr(io.StringIO()):
        try:
            aggregate_datasets([opts.repo_id] * len(shards), opts.repo_id, roots=[s.out for s in shards],
                               aggr_root=opts.out)
        except Exception as exc:  # noqa: BLE001 - LeRobot raises ValueError, OSError, av errors...
            shutil.rmtree(opts.out, ignore_errors=True)
            raise ExportError(f"merging the exported shards failed: {first_line(exc)}") from None


# -- local worker processes -----------------------------------------------------


def _run_processes(shards: list[_Shard], opts: ExportOptions, workers: int, bar) -> tuple[list, bool, float]:
    """Shards in spawned processes: (each shard's summary or None, interrupted, when the workers were ready).

    Start-up (spawn, LeRobot's import: seconds) is timed apart from the export, as in one process.
    """
    ctx = multiprocessing.get_context("spawn")  # a GL context does not survive fork
    progress = ctx.Queue()
    results: list[ExportSummary | None] = [None] * len(shards)
    shown = [0] * len(shards)  # frames of each shard already on the bar
    workers = min(workers, len(shards))
    interruptible = signal.getsignal(signal.SIGINT) is signal.default_int_handler  # not when started ignoring it
    pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_init_worker, initargs=(progress, interruptible))
    futures: dict[Future, int] = {}
    interrupted = False
    clean = False
    try:
        ready = [pool.submit(_ready) for _ in range(workers)]
        _lerobot()  # the driver's own import (for the merge) overlaps the workers'
        for future in ready:
            _result(future, "starting")
        t0 = time.perf_counter()
        bar.set_description(f"{len(shards)} shards on {workers} workers")
        bar.reset()  # the rate counts from here, not from the workers' start-up
        futures = {pool.submit(_export_shard, s.files, replace(opts, out=s.out), s.index): s.index for s in shards}
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
                _drain(progress, bar, shown)
                for future in done:
                    i = futures[future]
                    results[i] = _result(future, f"exporting shard {i} ({shards[i].files[0].name}...)")
                    bar.update(results[i].frames - shown[i])
                    shown[i] = results[i].frames
        except KeyboardInterrupt:
            # The terminal's Ctrl-C reached the workers too: each finalizes the episodes it saved
            # and returns. Wait for those, start nothing new, keep what finished.
            interrupted = True
            with _no_interrupt():
                for future in futures:
                    future.cancel()
                wait([f for f in futures if not f.cancelled()])
                for future, i in futures.items():
                    if results[i] is None and future.done() and not future.cancelled() and future.exception() is None:
                        results[i] = future.result()
        clean = True
    finally:
        if not clean:  # an error: the running shards' work is lost anyway, stop them now
            _stop_workers(pool)
        with _no_interrupt():  # the shards are done: a Ctrl-C now must not lose them
            pool.shutdown(wait=True, cancel_futures=True)
        progress.close()
    return results, interrupted, t0


def _result(future: Future, doing: str):
    try:
        return future.result()
    except BrokenProcessPool:
        raise ExportError(f"a worker process died {doing}; try fewer workers") from None


def _drain(progress, bar, shown: list[int]) -> None:
    while True:
        try:
            index, frames = progress.get_nowait()
        except Exception:  # noqa: BLE001 - queue.Empty, or a closed queue
            return
        if frames > shown[index]:
            bar.update(frames - shown[index])
            shown[index] = frames


def _stop_workers(pool: ProcessPoolExecutor) -> None:
    # ProcessPoolExecutor.terminate_workers() comes with Python 3.14; until then, its process table.
    for process in list((getattr(pool, "_processes", None) or {}).values()):
        with contextlib.suppress(Exception):
            process.terminate()


# -- Ray --------------------------------------------------------------------------


def _connect_ray(address: str):
    """replay.cluster's connect_ray, its one-line errors as ExportErrors (what export_dataset raises)."""
    try:
        return connect_ray(address)
    except ClusterError as exc:
        raise ExportError(str(exc)) from None


def _run_ray(ray, shards: list[_Shard], opts: ExportOptions, parallel: int, bar) -> tuple[list, bool, float]:
    """Shards as Ray tasks, at most 2 x parallel in flight (each holds its episodes' bytes)."""
    _lerobot()  # for the merge; before the clock starts, as in one process
    t0 = time.perf_counter()
    task = ray.remote(num_cpus=1, max_retries=0)(_ray_shard)
    results: list[ExportSummary | None] = [None] * len(shards)
    todo = list(shards)
    running: dict = {}
    clean = False
    try:
        while todo or running:
            while todo and len(running) < 2 * parallel:
                shard = todo.pop(0)
                files = [(f.name, f.read_bytes()) for f in shard.files]
                running[task.remote(files, opts)] = shard
            done, _ = ray.wait(list(running), num_returns=1)
            for ref in done:
                shard = running.pop(ref)
                summary, blob = _ray_result(ray, ref, shard)
                if blob:
                    shard.out.mkdir(parents=True)
                    _untar(blob, shard.out)
                results[shard.index] = summary
                bar.update(summary.frames)
        clean = True
    except KeyboardInterrupt:
        return results, True, t0  # the shards that came back are kept; the running ones are cancelled below
    finally:
        if not clean:
            for ref in running:
                with contextlib.suppress(Exception):
                    ray.cancel(ref, force=True)
    return results, False, t0


def _ray_result(ray, ref, shard: _Shard) -> tuple[ExportSummary, bytes]:
    try:
        return ray.get(ref)
    except ray.exceptions.RayTaskError as exc:
        cause = exc.cause
        if isinstance(cause, ExportError):
            raise ExportError(str(cause)) from None
        raise ExportError(f"shard {shard.index} ({shard.files[0].name}...) failed on Ray: "
                          f"{first_line(cause or exc)[:200]}") from None
    except ray.exceptions.RayError as exc:  # a worker or node lost
        raise ExportError(f"shard {shard.index} ({shard.files[0].name}...) failed on Ray: {first_line(exc)[:200]}") from None
