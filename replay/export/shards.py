"""Export in parallel: shards of episodes exported in worker processes or Ray tasks, merged by LeRobot.

Each shard is a contiguous run of the chosen episodes, exported by the ordinary
single-process export (`export_serial`) into a dataset of its own under a temporary
directory beside the output. LeRobot's `aggregate_datasets` then joins the shards in
order (parquet data re-indexed, videos joined by stream copy, episode metadata, tasks,
statistics) into the output, so it holds the frames, values and features one process
would have written. Local workers never fork from the driver (an OpenGL context does not
survive a fork): they fork from multiprocessing's fork server, which imported LeRobot once
for all of them. Ray tasks get the episode files as bytes and send their shard back as a
tar, so a cluster needs no shared file system, only this package installed on its nodes.

LeRobot and Ray are optional extras, imported only when an export starts.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import itertools
import json
import shutil
import sys
import tarfile
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from recorder.disk import write_failure_in, write_text_whole
from replay.errors import first_line
from replay.export.choose import export_units, select_episodes, wants_intervention, wants_variation_meta
from replay.export.codecs import video_decoder
from replay.export.lerobot_io import LEROBOT_HINT, ExportError, dir_size, load_lerobot
from replay.export.options import ExportOptions, ExportSummary
from replay.export.pieces import is_interrupted
from replay.export.serial import export_serial, operator_meta
from scenes.workers import ClusterError, Runner, WorkerLost, shielded, worker_context

# Two shards per worker even out episodes of different lengths, once there are enough episodes for
# that to matter; each shard costs ~1 s more in the merge (LeRobot loads its episode metadata).
SHARDS_PER_WORKER = 2
# What the local workers' fork server imports once for all of them (LeRobot's dataset: seconds of CPU each)
SHARD_PRELOAD = (__name__, "lerobot.datasets.lerobot_dataset", "av")


@dataclass
class _Shard:
    index: int
    files: list[Path]
    frames: int
    out: Path  # the shard's dataset, under the temporary parts directory
    plan: tuple[tuple[int, int | None], ...] = ()  # its variants: (index in `files`, look index or None)


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


def _init_worker(progress) -> None:
    """A local worker's start: the progress queue, and LeRobot loaded (seconds) before the clock starts."""
    global _progress
    _progress = progress
    load_lerobot()


def _export_shard(files: list[Path], opts: ExportOptions, index: int, cancel: threading.Event | None) -> ExportSummary:
    """One shard with the single-process export; after each saved episode the driver's bar moves.

    Once the driver drains the workers (Ctrl-C), `cancel` ends it as a Ctrl-C ends a
    single-process export: the saved episodes are kept.
    """
    queue = _progress

    def report(episodes: int, frames: int) -> None:
        if queue is not None:
            queue.put((index, frames))

    return export_serial(files, replace(opts, on_episode=report), log=lambda line: None, cancel=cancel)


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
        summary = export_serial(paths, replace(opts, out=out), log=lambda line: None)
        return summary, (_tar(out) if out.exists() else b"")


def _tar(directory: Path) -> bytes:
    buffer = io.BytesIO()
    with tarfile.open(fileobj=buffer, mode="w") as tar:
        tar.add(directory, arcname=".")
    return buffer.getvalue()


def _untar(data: bytes, directory: Path) -> None:
    with tarfile.open(fileobj=io.BytesIO(data), mode="r") as tar:
        tar.extractall(directory, filter="data")


# -- resuming: the parts folder beside the dataset ---------------------------------------------
# A parallel export writes its shards into `.NAME.parts/` beside the dataset, with plan.json (the
# episodes, the options, which episodes each shard holds) and `shard_NNN.done` once a shard is whole.
# A handled end (done, Ctrl-C, an error) removes the folder; after a kill -9 it stays, and --resume
# exports only what is missing: whole shards are kept, a shard cut short continues from its last
# whole piece, and the merge runs again.


def parts_dir(out: Path) -> Path:
    return out.parent / f".{out.name}.parts"


def _plan_options(opts: ExportOptions) -> dict:
    keys = ("repo_id", "cameras", "image_size", "action", "task", "only_success", "video", "vcodec", "object_state",
            "piece_episodes")
    plan = {k: (list(v) if isinstance(v := getattr(opts, k), tuple) else v) for k in keys}
    if opts.add_cameras:  # only then: plans written before the option existed stay resumable
        plan["add_cameras"] = list(opts.add_cameras)
    if opts.variation_key is not None:  # likewise
        plan["variation"] = opts.variation_key
    if opts.drop_idle:  # likewise
        plan["drop_idle"] = True
    return plan


def _parts(opts: ExportOptions, chosen: list, runs: list[range], log: Callable[[str], None]
           ) -> tuple[Path, list[range], dict[int, ExportSummary]]:
    """The parts folder, the shards' episode runs, and the shards already whole (when resuming)."""
    parts = parts_dir(opts.out)
    episodes = [str(Path(e.path).resolve()) for e in chosen]
    plan_file = parts / "plan.json"
    if not plan_file.is_file():
        if opts.resume:
            raise ExportError(f"--resume: {opts.out} holds no interrupted parallel export (no {parts.name}/plan.json)")
        shutil.rmtree(parts, ignore_errors=True)
        parts.mkdir()
        plan = {"episodes": episodes, "options": _plan_options(opts), "runs": [[r.start, r.stop] for r in runs]}
        tmp = parts / "plan.json.tmp"
        tmp.write_text(json.dumps(plan))
        tmp.replace(plan_file)
        return parts, runs, {}
    if not opts.resume:
        raise ExportError(f"{opts.out} holds a parallel export that was interrupted: add --resume to continue it "
                          f"(or remove {parts})")
    plan = json.loads(plan_file.read_text())
    if plan["episodes"] != episodes or plan["options"] != _plan_options(opts):
        raise ExportError(f"--resume: {opts.out} was exported from other episodes or options; give the same ones")
    runs = [range(a, b) for a, b in plan["runs"]]
    finished = {}
    for i in range(len(runs)):
        done = parts / f"shard_{i:03d}.done"
        if done.is_file():
            finished[i] = ExportSummary(out=parts / f"shard_{i:03d}", **json.loads(done.read_text()))
    if opts.out.exists():  # killed while merging: the merge runs again
        shutil.rmtree(opts.out)
    log(f"resuming {opts.out}: {len(finished)} of {len(runs)} shards were exported whole")
    return parts, runs, finished


def _mark_done(shard: "_Shard", result: ExportSummary) -> None:
    fields = {"episodes": result.episodes, "frames": result.frames, "fps": result.fps, "backend": result.backend,
              "dataset_episodes": result.dataset_episodes, "idle_dropped": result.idle_dropped}
    tmp = shard.out.parent / f"shard_{shard.index:03d}.done.tmp"
    tmp.write_text(json.dumps(fields))
    tmp.replace(shard.out.parent / f"shard_{shard.index:03d}.done")


# -- the driver -------------------------------------------------------------


def export_parallel(paths: list, opts: ExportOptions, log: Callable[[str], None],
                    cancel: threading.Event | None = None) -> ExportSummary:
    """`export_dataset` with opts.workers > 1 or opts.ray: shards in parallel, then LeRobot's aggregation.

    Cancelled (the token, or a KeyboardInterrupt), local workers end their shard as one
    process would (saved episodes kept), Ray tasks are cancelled, and the shards that came
    back whole, in order, are merged.
    """
    if opts.append:
        raise ExportError("appending runs in one process: leave out workers/Ray with append "
                          "(or export to a new directory in parallel)")
    if opts.ray is not None and not opts.ray.strip():
        raise ExportError("Ray address is empty: give auto, HOST:PORT or ray://HOST:PORT")
    chosen, summary = select_episodes(paths, opts, log)
    _check_installed("lerobot", LEROBOT_HINT)  # the full import (seconds) overlaps the workers' start
    runner = _runner(opts, opts.workers, cancel) if opts.ray is not None else None  # connects: a bad address fails now
    parallel = runner.workers if runner is not None else opts.workers
    units = export_units(chosen, opts)  # each episode once per look: variants are sharded like episodes
    runs = split([u.steps for u in units], shard_count(len(units), parallel))
    # The shards' own settings: what the driver resolved, no progress or callbacks of their own.
    shard_opts = replace(opts, cameras=summary.cameras, only_success=False, progress=False, on_episode=None,
                         workers=1, ray=None, append=False, resume=False, intervention=wants_intervention(opts, chosen),
                         variation_meta=wants_variation_meta(opts, chosen), operator_meta=operator_meta(opts, chosen))
    opts.out.parent.mkdir(parents=True, exist_ok=True)
    parts, runs, finished = _parts(opts, chosen, runs, log)
    shards = [_shard(i, [units[k] for k in run], parts / f"shard_{i:03d}") for i, run in enumerate(runs)]
    bar = _bar(opts, sum(s.frames for s in shards), len(shards), parallel)
    progress = None
    try:
        if runner is None:  # local processes, each with a queue back to the bar
            progress = worker_context().Queue()
            runner = _runner(opts, min(parallel, len(shards)), cancel, progress)
        with runner:
            results, interrupted, t0 = _run(runner, shards, shard_opts, bar, progress, finished)
        keep = _prefix(shards, results)
        summary.interrupted = interrupted or len(keep) < len(shards)
        bar.set_description("merging shards")
        shielded(lambda: _merge(opts, [shards[i] for i, _ in keep]))  # a Ctrl-C (a second one) must not cut it short
    finally:
        bar.close()
        if progress is not None:
            progress.close()
        shutil.rmtree(parts, ignore_errors=True)
    summary.seconds = time.perf_counter() - t0
    summary.episodes = sum(r.episodes for _, r in keep)
    summary.frames = sum(r.frames for _, r in keep)
    summary.idle_dropped = sum(r.idle_dropped for _, r in keep)
    summary.backend = next((r.backend for _, r in keep if r.backend), "")
    if opts.out.exists():
        from lerobot.datasets import LeRobotDatasetMetadata  # optional extra, loaded by the merge already

        summary.dataset_episodes = LeRobotDatasetMetadata(opts.repo_id, root=opts.out).total_episodes
        summary.bytes = dir_size(opts.out)
    decoder, why = video_decoder()
    if why and opts.video and summary.cameras and summary.episodes:
        log(f"video: {decoder} decoder ({why})")  # as the single-process export says it
    return summary


def _shard(index: int, units: list, out: Path) -> _Shard:
    """A shard of consecutive variants: the episode files they need, once each, and which variant of which file."""
    files = list(dict.fromkeys(u.path for u in units))
    plan = tuple((files.index(u.path), u.look) for u in units)
    return _Shard(index, files, sum(u.steps for u in units), out, plan)


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
        if result.episodes + result.resumed_from and shard.out.exists():
            keep.append((shard.index, result))
        if result.interrupted or result.episodes + result.resumed_from < len(shard.plan):
            break
    return keep


def _merge(opts: ExportOptions, shards: list[_Shard]) -> None:
    """LeRobot's aggregation of the shard datasets, in order, into opts.out (nothing when no shard has episodes)."""
    if not shards:
        return
    load_lerobot()  # its logging settings, as the shards had them
    from lerobot.datasets.aggregate import aggregate_datasets  # optional extra: pip install '...[lerobot]'

    # aggregate_datasets shows tqdm bars of its own ("Copy data and videos") on stderr: ours is the one bar.
    with contextlib.redirect_stderr(io.StringIO()):
        try:
            aggregate_datasets([opts.repo_id] * len(shards), opts.repo_id, roots=[s.out for s in shards],
                               aggr_root=opts.out)
            _restate_indices(opts.out)
        except Exception as exc:  # noqa: BLE001 - LeRobot raises ValueError, OSError, av errors...
            shutil.rmtree(opts.out, ignore_errors=True)
            raise ExportError(f"merging the exported shards failed: {first_line(exc)}") from None


INDEX_COLUMNS = ("index", "episode_index", "task_index")  # renumbered by the merge; frame_index is not


def _restate_indices(root: Path) -> None:
    """The merged dataset's statistics of the columns the merge renumbers, from their merged values.

    LeRobot's aggregate_datasets renumbers `index`, `episode_index` and `task_index` in the data but aggregates
    each shard's statistics of them as the shard wrote them (each shard counts from 0: a dataset of 7 episodes
    said episode_index max 3). Recomputed here per episode and aggregated, with LeRobot's functions, as a
    serial export computes them.
    """
    import pyarrow.parquet as pq
    from lerobot.datasets.compute_stats import aggregate_stats, compute_episode_stats
    from lerobot.datasets.io_utils import load_stats
    from lerobot.datasets.utils import STATS_PATH, serialize_dict

    stats = load_stats(root)
    info = json.loads((root / "meta" / "info.json").read_text())
    columns = [c for c in INDEX_COLUMNS if c in info["features"] and c in (stats or {})]
    if "episode_index" not in columns:  # LeRobot's datasets always have it: nothing of ours to restate
        return
    table = pq.read_table(sorted((root / "data").rglob("*.parquet")), columns=columns)
    episodes = table.column("episode_index").to_numpy()
    order = np.argsort(episodes, kind="stable")  # the rows of each episode together, in their order
    values = {c: table.column(c).to_numpy()[order] for c in columns}
    _, starts = np.unique(episodes[order], return_index=True)
    ends = [*starts[1:], len(order)]
    features = {c: info["features"][c] for c in columns}
    per_episode = [compute_episode_stats({c: v[a:b] for c, v in values.items()}, features) for a, b in zip(starts, ends)]
    stats.update(aggregate_stats(per_episode))
    write_text_whole(root / STATS_PATH, json.dumps(serialize_dict(stats), indent=4))  # whole, or the old one


# -- running the shards --------------------------------------------------------


def _runner(opts: ExportOptions, workers: int, cancel: threading.Event | None, progress=None) -> Runner:
    """The shards' runner: `workers` local processes (even one: shards never run in the driver), or Ray."""
    try:
        if opts.ray is not None:
            return Runner(workers, ray=opts.ray, ray_options={"max_retries": 0}, cancel=cancel)
        return Runner(workers, setup=_init_worker, setup_args=(progress,), cancel=cancel, processes=True,
                      preload=SHARD_PRELOAD)
    except ClusterError as exc:  # no Ray, or nothing at the address: one line, as export_dataset raises
        raise ExportError(str(exc)) from None


def _run(runner: Runner, shards: list[_Shard], opts: ExportOptions, bar, progress,
         finished: dict[int, ExportSummary]) -> tuple[list, bool, float]:
    """Each shard's summary (None where it did not run), whether interrupted, and when the workers were ready.

    `finished`: shards an interrupted run already exported whole (--resume); the others run, a shard
    that was cut short continuing from its last whole piece (its journal).

    Start-up (the workers' start, LeRobot's import: seconds) is timed apart from the export, as in one
    process. On Ray at most 2 x the workers' shards are in flight (each holds its episodes' bytes).
    """
    ray = runner.backend == "ray"
    results: list[ExportSummary | None] = [finished.get(i) for i in range(len(shards))]
    shown = [r.frames if r is not None else 0 for r in results]  # frames of each shard already on the bar
    todo = [s for s in shards if results[s.index] is None]
    load_lerobot()  # the driver's own import (for the merge) overlaps the workers'
    try:
        runner.wait_started()
    except WorkerLost:
        raise ExportError("a worker process died starting; try fewer workers") from None
    t0 = time.perf_counter()
    if not ray:
        bar.set_description(f"{len(shards)} shards on {runner.workers} workers")
        bar.reset()  # the rate counts from here, not from the workers' start-up

    bar.update(sum(shown))

    def calls():
        for s in todo:
            if ray:
                shutil.rmtree(s.out, ignore_errors=True)  # a Ray shard comes back whole or not at all
                yield _ray_shard, [(f.name, f.read_bytes()) for f in s.files], replace(opts, variant_plan=s.plan)
            else:
                if s.out.exists() and not is_interrupted(s.out):
                    shutil.rmtree(s.out)  # whole, but killed before it was marked done: exported again
                yield (_export_shard, s.files, replace(opts, out=s.out, resume=is_interrupted(s.out), variant_plan=s.plan), s.index,
                       runner.cancel_arg)

    def take(position: int, result) -> None:
        index = todo[position].index
        if ray:
            result, blob = result
            if blob:
                shards[index].out.mkdir(parents=True)
                _untar(blob, shards[index].out)
        results[index] = result
        if not result.interrupted:
            _mark_done(shards[index], result)
        bar.update(result.frames - shown[index])
        shown[index] = result.frames

    poll = (lambda: _drain(progress, bar, shown)) if progress is not None else None
    try:
        for index, result in enumerate(runner.results(calls(), 2 * runner.workers, poll)):
            take(index, result)
    except KeyboardInterrupt:
        # Local workers end their shard keeping the episodes they saved; Ray tasks are cancelled.
        # Start nothing new, keep what finished.
        for index, result in sorted(runner.drain().items()):
            if results[index] is None:
                take(index, result)
        return results, True, t0
    except ExportError:
        raise
    except Exception as exc:  # noqa: BLE001 - a worker lost, or a shard's error on Ray
        if runner.backend == "local" and write_failure_in(exc) is not None:
            with contextlib.suppress(Exception):  # a full disk: the other shards end early, their workers
                runner.drain()  # exit whole (not terminated mid-write); the caller removes the shards
        raise _shard_error(runner, shards, exc) from None
    return results, False, t0


def _shard_error(runner: Runner, shards: list[_Shard], exc: Exception) -> Exception:
    """A shard's failure as one line (an error in a local shard is a bug: it keeps its traceback)."""
    shard = shards[runner.failed] if runner.failed is not None else None
    what = f"shard {shard.index} ({shard.files[0].name}...)" if shard is not None else "a shard"
    if runner.backend == "ray":
        return ExportError(f"{what} failed on Ray: {first_line(exc)[:200]}")
    if isinstance(exc, WorkerLost):
        return ExportError(f"a worker process died exporting {what}; try fewer workers")
    return exc


def _drain(progress, bar, shown: list[int]) -> None:
    while True:
        try:
            index, frames = progress.get_nowait()
        except Exception:  # noqa: BLE001 - queue.Empty, or a closed queue
            return
        if frames > shown[index]:
            bar.update(frames - shown[index])
            shown[index] = frames
