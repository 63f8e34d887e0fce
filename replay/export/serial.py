"""Export recorded episodes to a LeRobot dataset in this process, rendering cameras from exact replay.

Works only from the recorded files and their stored model XML: each recorded
state is restored (mj_setState + mj_forward) and rendered offscreen, so any
camera at any size can be chosen after the fact and the teleop loop never paid
for rendering. Everything is written through LeRobot's own API
(`LeRobotDataset.create` / `resume`, `add_frame`, `save_episode`, `finalize`),
and `finalize` runs whatever happens, Ctrl-C included: an unfinalized dataset
loses every episode in its open parquet file.

What to export is chosen in choose.py, the dataset opened in lerobot_dataset.py; this module is the
loop: pieces, episodes, frames. LeRobot is an optional extra, imported only when an export starts.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

from recorder.disk import check_free_space
from replay.episode import Episode, EpisodeError, load_episode
from replay.export.choose import export_units, select_episodes, wants_intervention, wants_object_state, wants_variation_meta
from replay.export.codecs import video_decoder
from replay.export.lerobot_dataset import open_dataset
from replay.export.lerobot_io import ExportError, dir_size, load_lerobot
from replay.export.looks import COLUMN, Unit, dataset_has_column, record_column, variant
from replay.export.operators import record_operator, wants_operator_column
from replay.export.options import ExportOptions, ExportSummary, added_cameras, check_options
from replay.export.pieces import export_in_pieces
from replay.export.review_meta import SUBTASK_FEATURE, SUBTASK_INDEX, dataset_has_review, record_review, review_for, subtask_ids_for
from replay.export.stats import image_stats
from replay.export.stream import EpisodeEnd, FrameStream
from replay.features import ENV_STATE, INTERVENTION, INTERVENTION_FEATURE, feature_key, features, is_channel_first, object_layout, robot_layout
from replay.render import RenderError, warm_up
from scenes.workers.interrupts import is_cancelled, shielded


def export_serial(paths: Iterable[str | Path], opts: ExportOptions, log: Callable[[str], None] | None = None,
                  cancel: threading.Event | None = None) -> ExportSummary:
    """Export the episodes under `paths` into the LeRobot dataset at opts.out in this process, in finalized
    pieces (see module doc; `replay.export.export_dataset` chooses this or the parallel shards).

    cancel: a token (the CLI sets it on Ctrl-C). Once set, or on a KeyboardInterrupt, the
    export stops: the episode in progress is dropped, the saved ones are finalized and kept
    (`interrupted` in the summary). An episode being saved is saved whole first.
    """
    log = log or (lambda line: print(line, file=sys.stderr))
    paths = list(paths)
    check_options(opts)
    warm_up()  # the GL backend probe runs while episodes are scanned and LeRobot loads
    chosen, summary = select_episodes(paths, opts, log)
    opts = replace(opts, variation_meta=wants_variation_meta(opts, chosen),  # one answer for every piece
                   operator_meta=operator_meta(opts, chosen))
    units = export_units(chosen, opts)
    t0 = time.perf_counter()
    logs = [log]  # the first piece's notes (the video decoder) are the export's; the same again are not

    frames_left = [sum(u.steps for u in units)]  # not yet exported by this run
    per_frame: list[float] = []  # dataset bytes per frame, measured on the first piece this run writes

    def piece(paths: list[Unit], piece_opts: ExportOptions) -> ExportSummary:
        if per_frame and not opts.force:  # before the next piece: the rest must clearly fit (issue 25)
            check_free_space(opts.out, per_frame[0] * frames_left[0], f"{frames_left[0]} more frames of "
                             f"~{per_frame[0] / 1000:.1f} KB")
        size0 = dir_size(opts.out) if opts.out.exists() else 0
        done = _export_piece(paths, piece_opts, logs.pop() if logs else (lambda line: None), cancel)
        frames_left[0] -= done.frames
        if not per_frame and done.frames:
            per_frame.append(max(0, (dir_size(opts.out) if opts.out.exists() else 0) - size0) / done.frames)
        return done

    parts, summary.resumed_from = export_in_pieces(units, opts, piece, log, opts.piece_episodes, names=[u.name for u in units])
    for part in parts:
        summary.episodes += part.episodes
        summary.frames += part.frames
        summary.idle_dropped += part.idle_dropped
        summary.interrupted = summary.interrupted or part.interrupted
        summary.backend = summary.backend or part.backend
    summary.seconds = time.perf_counter() - t0
    summary.dataset_episodes = parts[-1].dataset_episodes if parts else summary.resumed_from
    summary.bytes = dir_size(opts.out) if opts.out.exists() else 0
    return summary


def _export_piece(units: list[Unit], opts: ExportOptions, log: Callable[[str], None],
                  cancel: threading.Event | None) -> ExportSummary:
    """One finalized piece: the variants `units` into a new dataset, or appended to opts.out's."""
    paths = list(dict.fromkeys(u.path for u in units))
    chosen, summary = select_episodes(paths, replace(opts, only_success=False), lambda line: None)
    robot_type = chosen[0].signature[0]
    fps, cameras = summary.fps, summary.cameras
    LeRobotDataset = load_lerobot()  # after the input checks: they answer at once, LeRobot takes seconds to import
    decoder, why = video_decoder()

    first = load_episode(chosen[0].path)
    added = added_cameras(opts)
    try:
        model = first.build_model(added)
    except EpisodeError as exc:
        raise ExportError(str(exc)) from None
    try:
        arms = robot_layout(first.meta, model)
    except (KeyError, ValueError) as exc:
        raise ExportError(f"{first.path}: robot_spec does not match the recorded model: {exc}") from None
    objects = object_layout(first.meta, model) if wants_object_state(opts) else None
    spec = features(arms, opts.action, cameras, opts.image_size, opts.video, objects=objects)
    if wants_intervention(opts, chosen):
        spec[INTERVENTION] = dict(INTERVENTION_FEATURE)
    if opts.subtasks:
        spec[SUBTASK_INDEX] = dict(SUBTASK_FEATURE)
    reviews = opts.accepted or bool(opts.reject_flags)
    if reviews and opts.append and opts.out.exists() and not dataset_has_review(opts.out):
        raise ExportError(f"cannot append: {opts.out} has no per-episode review metadata; export what passed review "
                          "to a new dataset")
    try:
        stream = FrameStream(model, opts.image_size, cameras)  # replays and renders in a thread of its own
    except RenderError as exc:
        raise ExportError(str(exc)) from None
    summary.backend = stream.backend
    # A streamed episode never waits on the encoder: its queue holds a whole episode.
    queue = max(e.steps for e in chosen) + 2
    t0 = time.perf_counter()
    column = wants_variation_meta(opts, chosen)
    if column and opts.append and opts.out.exists() and not dataset_has_column(opts.out):
        stream.close()
        raise ExportError(f"cannot append: {opts.out} has no per-episode {COLUMN} metadata, and these episodes vary "
                          "(their looks or physics); export them to a new dataset")
    try:
        ds, created = open_dataset(LeRobotDataset, opts, spec, fps, robot_type, queue, decoder)
    except BaseException:
        stream.close()
        raise
    if why and opts.video and cameras:  # once the export goes ahead: an error stays the one line
        log(f"video: {decoder} decoder ({why})")  # slower reads in training, nothing wrong
    try:
        with image_stats():  # LeRobot's per-frame image statistics, from value counts (replay/export/stats.py)
            by_path = {e.path: e.operator for e in chosen}
            operators = [by_path.get(u.path) for u in units] if operator_meta(opts, chosen) else None
            _write(ds, units, first, opts, cameras, stream, summary, cancel, column, operators, reviews)
    except KeyboardInterrupt:
        summary.interrupted = True
    finally:
        _finish(ds, stream)
        summary.seconds = time.perf_counter() - t0
        if created and summary.episodes == 0 and opts.out.exists():
            shutil.rmtree(opts.out, ignore_errors=True)  # nothing saved: leave no half dataset behind
    summary.dataset_episodes = ds.meta.total_episodes
    summary.bytes = dir_size(opts.out) if opts.out.exists() else 0
    return summary


def operator_meta(opts: ExportOptions, chosen: list) -> bool:
    """Whether the export writes the `operator` episode column: as resolved, else replay/export/operators.py's rule."""
    if opts.operator_meta is not None:
        return opts.operator_meta
    return wants_operator_column([e.operator for e in chosen], opts.out, opts.append)


def _loader(path: Path) -> Callable[[], Episode]:
    def load() -> Episode:
        try:
            return load_episode(path)
        except EpisodeError as exc:  # changed on disk since the scan
            raise ExportError(str(exc)) from None

    return load


def _loaders(units: list[Unit], first: Episode) -> list[Callable[[], Episode]]:
    """One loader per variant; the variants of one episode share its one load."""
    last = {"path": units[0].path, "episode": first}

    def loader(path: Path) -> Callable[[], Episode]:
        def load() -> Episode:
            if last["path"] != path:
                last["episode"], last["path"] = None, path
                last["episode"] = _loader(path)()
            return last["episode"]

        return load

    return [loader(u.path) for u in units]


def _write(ds, chosen: list[Unit], first: Episode, opts: ExportOptions, cameras, stream: FrameStream,
           summary: ExportSummary, cancel: threading.Event | None, column: bool = False,
           operators: list[str | None] | None = None, reviews: bool = False) -> None:
    """LeRobot's side: add the stream's frames, save each episode as its last frame arrives.

    `chosen`: the variants, in order; `column`: write each one's `variation` episode metadata;
    `operators`: each one's operator, written as the `operator` column (None: no such column).
    Cancelled (the token, or a KeyboardInterrupt), it ends with KeyboardInterrupt between
    frames; the episode in progress is dropped.
    """
    from tqdm import tqdm

    keys = [feature_key(c) for c in cameras]
    channel_first = [is_channel_first(ds.meta.features[k]) for k in keys]  # as the dataset declares them
    added = tuple(added_cameras(opts))
    prepare = None
    if column or any(u.look is not None for u in chosen):
        prepare = [(lambda ep, model, look=u.look: variant(ep, model, look, opts.looks, opts.variation, added)) for u in chosen]
    next_variation = record_column(ds) if column else None
    next_operator = record_operator(ds) if operators is not None else None
    next_review = record_review(ds) if reviews else None
    subtasks = None
    if SUBTASK_INDEX in ds.meta.features:
        subtasks = lambda ep: subtask_ids_for(opts.extras, opts.subtasks, ep)  # noqa: E731
    stream.start(_loaders(chosen, first), opts.action, lambda ep: opts.task or ep.meta.task or ep.meta.scene or "task", keys,
                 channel_first, intervention=INTERVENTION in ds.meta.features, objects=ENV_STATE in ds.meta.features,
                 cameras_added=added, prepare=prepare, drop_idle=opts.drop_idle, subtasks=subtasks)
    total = sum(e.steps for e in chosen)
    bar = tqdm(total=total, unit="frame", desc=f"episode 1/{len(chosen)}", disable=not opts.progress,
               file=sys.stderr, dynamic_ncols=True)
    try:
        for item in stream:
            if is_cancelled(cancel):
                raise KeyboardInterrupt
            if not isinstance(item, EpisodeEnd):
                ds.add_frame(item)
                bar.update(1)
                continue
            if next_variation is not None:
                next_variation(item.variation or {})
            if next_operator is not None:
                next_operator(operators[item.index])
            if next_review is not None:
                next_review(review_for(opts.extras, chosen[item.index].path))
            # LeRobot's save_episode writes data, video and metadata in turn; cut in between, the
            # dataset would hold frames its metadata does not know of: a Ctrl-C waits for it.
            _, interrupted = shielded(ds.save_episode)
            summary.episodes += 1
            summary.frames += item.steps
            summary.idle_dropped += item.dropped
            bar.update(item.dropped)  # the bar counts recorded steps
            if item.index + 1 < len(chosen):
                bar.set_description(f"episode {item.index + 2}/{len(chosen)}")
            if opts.on_episode is not None:
                opts.on_episode(summary.episodes, summary.frames)
            if interrupted or is_cancelled(cancel):
                raise KeyboardInterrupt
    except BaseException:
        try:
            pending = ds.has_pending_frames()
        except KeyError:  # the buffer was half taken apart by save_episode (LeRobot pops its "size")
            pending = True
        if pending:  # the episode in progress is dropped, the saved ones stay
            ds.clear_episode_buffer()
        raise
    finally:
        bar.close()


def _finish(ds, stream: FrameStream) -> None:
    """Stop the stream, then finalize(), with a Ctrl-C held meanwhile: cutting it short would lose saved episodes."""

    def finish() -> None:
        try:
            stream.close()
        finally:
            ds.finalize()

    shielded(finish)

