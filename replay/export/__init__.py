"""Recorded episodes into LeRobot datasets. `export_dataset` is the one entry: one process (serial.py, in
pieces) or shards (shards.py).

- options.py: `ExportOptions` (the flags) and their checks, `ExportSummary`;
- choose.py: which episodes, cameras and optional features; codecs.py: video encoder and decoder;
- lerobot_dataset.py: opening the dataset (new, or appended to); lerobot_io.py: importing LeRobot;
- serial.py: the loop; stream.py: replay and rendering in a thread; stats.py: image statistics;
- pieces.py: finalized, resumable pieces; shards.py: parallel shards; looks.py: looks (variants);
  preview.py: the preview sheet. The frame's schema is replay/features.py (learning shares it).
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Iterable
from dataclasses import replace
from pathlib import Path

from recorder.disk import WriteError, cause, write_failure_in
from replay.export.lerobot_io import ExportError
from replay.export.options import ExportOptions, ExportSummary, check_options
from replay.export.pieces import is_interrupted
from replay.export.review_meta import resolve_extras, write_subtasks_file
from replay.export.serial import export_serial
from replay.export.shards import export_parallel


def export_dataset(paths: Iterable[str | Path], opts: ExportOptions, log: Callable[[str], None] | None = None,
                   cancel: threading.Event | None = None) -> ExportSummary:
    """Export the episodes under `paths` into the LeRobot dataset at opts.out: in this process, or with
    opts.workers > 1 or opts.ray in shards exported in parallel and merged with LeRobot's aggregation.

    cancel: a token (the CLI sets it on Ctrl-C). Once set, or on a KeyboardInterrupt, the
    export stops: the episode in progress is dropped, the saved ones are finalized and kept
    (`interrupted` in the summary). An episode being saved is saved whole first.
    """
    log = log or (lambda line: print(line, file=sys.stderr))
    check_options(opts)
    paths = list(paths)
    try:
        extras, subtasks = resolve_extras(paths, opts.accepted, opts.reject_flags, opts.out, opts.append or opts.resume)
        opts = replace(opts, extras=extras, subtasks=subtasks)
        if opts.workers > 1 or opts.ray is not None:
            summary = export_parallel(paths, opts, log, cancel)
        else:
            summary = export_serial(paths, opts, log, cancel)
        if opts.out.is_dir() and (opts.out / "meta").is_dir():
            write_subtasks_file(opts.out, opts.subtasks)  # LeRobot's meta/subtasks.parquet, for every piece and shard
        return summary
    except ExportError:
        raise
    except Exception as exc:  # noqa: BLE001 - a full disk reaches here as OSError, or LeRobot's RuntimeError
        failure = write_failure_in(exc)
        if failure is None:
            raise
        detail = str(failure) if isinstance(failure, WriteError) else f"{failure.filename or opts.out}: {cause(failure)}"
        raise ExportError(f"{detail}; {_what_is_left(opts)}") from None


def _what_is_left(opts: ExportOptions) -> str:
    """After a write error: what the dataset directory holds now, and how to go on."""
    if is_interrupted(opts.out):
        return ("the pieces finished before are kept: free some space, then run the same command with --resume "
                "to continue")
    if opts.append:
        return f"{opts.out} is as it was before"
    return "nothing was kept" if not opts.out.exists() else f"{opts.out} was left as it is"


__all__ = ["ExportError", "ExportOptions", "ExportSummary", "export_dataset"]
