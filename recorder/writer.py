"""EpisodeWriter: cheap append on the control thread, encoding and IO on a writer thread.

The control loop writes each step straight into the next row of a preallocated
block (`claim`, fill in place, `commit`: no temporaries, one copy per field), or
hands a StepRecord to `append`, which does the same. A daemon thread copies the
committed rows out every FLUSH_PERIOD seconds, encodes them into every format and
flushes the files to the OS, so a kill -9 loses at most about FLUSH_PERIOD plus
one batch's write time.
An episode left open at interpreter exit (Ctrl-C, an exception) is closed as
incomplete by an atexit hook, so what was recorded is kept.
The first write error (a full disk, a file size limit) stops the writer thread;
`claim` and `close` then raise a one-line RecorderError naming the file and the
cause, and every file keeps what reached it (readers see it as cut short).
"""

from __future__ import annotations

import atexit
import json
import re
import threading
import time
import weakref
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from recorder.hdf5_sink import ALONGSIDE_MCAP_PERIOD, WRITE_PERIOD, Hdf5Sink
from recorder.mcap_sink import McapSink
from recorder.step import StepRecord, pack_into
from recorder import format as schema
from recorder.format import EpisodeMeta, Outcome
from scenes.errors import TeleopError, first_line

FORMATS = ("mcap", "hdf5")
SUFFIX = {"mcap": ".mcap", "hdf5": ".hdf5"}
FLUSH_PERIOD = 0.1  # s; a kill -9 loses about this plus one batch's encoding (0.25 s promised); each flush costs ~1 ms of CPU
BLOCK_ROWS = 256  # rows preallocated at a time (~10 s at 25 Hz); drained blocks are let go
_EPISODE_RE = re.compile(r"^episode_(\d+)\.(mcap|hdf5)$")
_open_writers: "weakref.WeakSet[EpisodeWriter]" = weakref.WeakSet()


class RecorderError(TeleopError, RuntimeError):
    """Recording failed (bad step shape, disk full, ...); the message is one line."""


def episode_path(directory: Path, index: int, fmt: str) -> Path:
    return Path(directory) / f"episode_{index:06d}{SUFFIX[fmt]}"


def next_episode_index(directory: Path) -> int:
    """One past the highest episode index in `directory` (0 when none).

    Never reuses a gap, so new episodes always sort after older ones.
    """
    directory = Path(directory)
    if not directory.is_dir():
        return 0
    found = [int(m.group(1)) for p in directory.iterdir() if (m := _EPISODE_RE.match(p.name))]
    return max(found) + 1 if found else 0


def _error_line(path: Path, exc: BaseException) -> str:
    """'<file>: <cause>' on one line: the OS's words for an OSError ("No space left on device")."""
    if isinstance(exc, OSError) and exc.strerror:
        return f"{path}: {exc.strerror}"
    return f"{path}: {first_line(exc)}"


def _commands_json(commands: list) -> str:
    """JSON list of a step's commands. Objects with to_dict() (device Commands) are
    accepted too, so a caller may leave the conversion to this thread."""
    if not commands:
        return "[]"
    return json.dumps([c if isinstance(c, dict) else c.to_dict() for c in commands])


def _new_episode_meta(meta: EpisodeMeta, index: int) -> EpisodeMeta:
    """What a new file says at its start: this schema version, this index, no outcome yet."""
    if not isinstance(meta, EpisodeMeta):
        raise RecorderError(f"episode metadata must be an EpisodeMeta, got {type(meta).__name__}")
    if not meta.model_xml:
        raise RecorderError("episode metadata lacks model_xml")
    return meta.replace(episode_index=index, schema_version=schema.SCHEMA_VERSION, outcome=Outcome())


class EpisodeWriter:
    """Records one episode into directory/episode_{index:06d}.{mcap,hdf5}."""

    def __init__(self, directory: Path, index: int, formats: Sequence[str], meta: EpisodeMeta):
        formats = list(dict.fromkeys(formats))
        bad = [f for f in formats if f not in FORMATS]
        if bad or not formats:
            raise RecorderError(f"formats must be among {FORMATS}, got {list(formats)}")
        meta = _new_episode_meta(meta, index)
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.index = index
        self.meta = meta
        self._width = meta.layout.width
        self.columns = meta.layout.slices  # where each field goes in a claimed row (StepLayout.slices)
        self._sinks: list[McapSink | Hdf5Sink] = []
        for fmt in formats:
            path = episode_path(self.directory, index, fmt)
            if path.exists():  # h5py does not always say FileExistsError
                raise RecorderError(f"{path}: episode file already exists")
        for fmt in formats:
            path = episode_path(self.directory, index, fmt)
            try:
                if fmt == "mcap":
                    self._sinks.append(McapSink(path, meta))
                else:
                    period = ALONGSIDE_MCAP_PERIOD if "mcap" in formats else WRITE_PERIOD
                    self._sinks.append(Hdf5Sink(path, meta, write_period=period))
            except FileExistsError:
                self._drop_files()
                raise RecorderError(f"{path}: episode file already exists") from None
            except OSError as exc:  # a full disk, no permission: name the file and the cause
                self._drop_files()
                raise RecorderError(_error_line(path, exc)) from None
            except BaseException:
                self._drop_files()
                raise
        self.steps = 0  # committed rows; the writer thread reads up to here
        self.cpu_seconds = 0.0  # writer-thread CPU spent encoding and writing, for benches
        self._blocks: list[np.ndarray | None] = [np.empty((BLOCK_ROWS, self._width))]
        self._row = 0  # next row in the last block
        self._commands: dict[int, list] = {}  # step -> its commands, for the (few) steps that have some
        self._drained = 0  # rows the writer thread has taken
        self._stop = threading.Event()
        self._error: BaseException | None = None  # the first write error; it stops the writer thread
        self._error_path: Path | None = None  # the file it happened in
        self._closed = False
        self._thread = threading.Thread(target=self._run, name=f"episode-writer-{index}", daemon=True)
        self._thread.start()
        _open_writers.add(self)

    @property
    def paths(self) -> list[Path]:
        return [s.path for s in self._sinks]

    def claim(self) -> np.ndarray:
        """The next step's row, a view to fill in place (fields at `self.columns`), then `commit`.

        Until commit, the row is not recorded; claiming again returns the same row.
        """
        if self._closed or self._error is not None:
            raise RecorderError(self._why_stopped())
        if self._row == BLOCK_ROWS:
            self._blocks.append(np.empty((BLOCK_ROWS, self._width)))
            self._row = 0
        return self._blocks[-1][self._row]

    def commit(self, commands: list = ()) -> None:
        """Record the claimed row, with the step's commands (dicts, or objects with to_dict())."""
        if commands:
            self._commands[self.steps] = list(commands)
        self._row += 1
        self.steps += 1  # last: the writer thread takes rows below this

    def append(self, step: StepRecord) -> None:
        """Record one step given as a StepRecord (arrays are copied; the caller may reuse them)."""
        row = self.claim()
        try:
            pack_into(row, step, self.columns)
        except ValueError as exc:  # a field of the wrong size or rank
            raise RecorderError(f"step does not fit the episode layout: {exc}") from None
        self.commit(step.commands)

    def close(self, success: bool, complete: bool) -> list[Path]:
        """Write what is queued, mark success/complete, finish the files."""
        if self._closed:
            return self.paths
        self._shutdown()
        if self._error is not None:  # every file keeps what reached it: a cut file reads as incomplete
            self._abort_sinks()
            raise RecorderError(self._why_stopped())
        self.meta = self.meta.with_outcome(success, complete, self.steps)
        end = self.meta.outcome
        for sink in self._sinks:
            if self._error is not None:  # an earlier file failed to finish: close this one as it is
                sink.abort()
                continue
            try:
                sink.finish(end)
            except Exception as exc:  # noqa: BLE001 - a full disk at the end; the file keeps its last flushed rows
                self._error, self._error_path = exc, sink.path
                sink.abort()
        if self._error is not None:
            raise RecorderError(self._why_stopped())
        return self.paths

    def discard(self) -> None:
        """Stop and delete this episode's files."""
        if not self._closed:
            self._shutdown()
        self._drop_files()

    # -- internals -------------------------------------------------------

    def _why_stopped(self) -> str:
        if self._error is not None:
            where = self._error_path or self.directory
            return f"{_error_line(where, self._error)} (episode {self.index} cut short; what was written is kept)"
        return f"episode {self.index} is already closed"

    def _shutdown(self) -> None:
        self._closed = True
        _open_writers.discard(self)
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        try:
            while not self._stop.wait(FLUSH_PERIOD):
                self._timed_drain()
            self._timed_drain()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller by append/close
            self._error = exc

    def _timed_drain(self) -> None:
        t0 = time.thread_time()
        self._drain()
        self.cpu_seconds += time.thread_time() - t0

    def _drain(self) -> None:
        end, start = self.steps, self._drained
        if end == start:
            return
        parts = []
        for i in range(start // BLOCK_ROWS, (end - 1) // BLOCK_ROWS + 1):
            lo, hi = max(start, i * BLOCK_ROWS), min(end, (i + 1) * BLOCK_ROWS)
            parts.append(self._blocks[i][lo - i * BLOCK_ROWS : hi - i * BLOCK_ROWS])
            if hi == (i + 1) * BLOCK_ROWS:
                self._blocks[i] = None  # full and taken: no longer needed (the copy below keeps the data)
        rows = np.concatenate(parts)
        pop = self._commands.pop
        commands = [_commands_json(pop(k, ())) for k in range(start, end)]  # encoded once for all sinks
        self._drained = end
        for i, sink in enumerate(self._sinks):
            if i:
                time.sleep(50e-6)  # let the control thread have the GIL between sinks (not after the last: a wake less)
            try:
                sink.write(rows, commands)
                sink.flush()
            except BaseException:
                self._error_path = sink.path  # _run keeps the error and stops: no file is written again
                raise

    def _abort_sinks(self) -> None:
        """Close every file without finishing it (sinks' abort never raises)."""
        for sink in self._sinks:
            sink.abort()

    def _drop_files(self) -> None:
        self._abort_sinks()
        for sink in self._sinks:
            sink.path.unlink(missing_ok=True)

    def __enter__(self) -> "EpisodeWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close(success=False, complete=True)
        elif not self._closed:
            self.close(success=False, complete=False)


@atexit.register
def _close_open_writers() -> None:
    """Interpreter exiting with an episode open: keep it, marked incomplete."""
    for writer in list(_open_writers):
        try:
            writer.close(success=False, complete=False)
        except Exception:  # noqa: BLE001 - exiting anyway; the file stays readable as truncated
            pass
