"""Writing where the disk may fill up: one line naming the file and the cause, nothing half-written.

Every command that writes (generate, export, annotate, convert, eval --record, the
replay viewer) turns an OSError (ENOSPC, EDQUOT, EFBIG, EACCES, EIO, ...) into a
`WriteError` whose message is '<file>: <the OS's words>', removes its temporary
file, and keeps whatever was complete before. A long job first compares the free
space with what it will need (estimated from its first episode or frame) and says
so in one line before it does the work, unless forced.
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import shutil
import tempfile
from pathlib import Path

from scenes.errors import TeleopError, first_line

PART = ".part"  # suffix of a file being written; renamed to its name once whole
SPACE_MARGIN = 0.9  # free space below this fraction of the estimate is "clearly below" (the estimate is rough)


class WriteError(TeleopError, OSError):
    """A file could not be written (a full disk, a quota, permissions): '<file>: <cause>', one line."""

    reason: str = ""  # the cause alone ("No space left on device")


class NotEnoughSpace(WriteError):
    """The free space is clearly below what a job will need; --force goes on anyway."""


def cause(exc: BaseException) -> str:
    """The OS's words for an OSError ("No space left on device"), else the error's first line."""
    if isinstance(exc, WriteError) and exc.reason:
        return exc.reason
    if isinstance(exc, OSError) and exc.errno:
        return os.strerror(exc.errno)  # the OS's words, not a library's wrapping of them
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return first_line(exc)


def write_error(path: str | Path, exc: BaseException) -> WriteError:
    """A WriteError '<path>: <cause>' (the file the OS names, when it names one, else `path`)."""
    if isinstance(exc, WriteError):
        return exc
    named = getattr(exc, "filename", None) if isinstance(exc, OSError) else None
    error = WriteError(f"{named or path}: {cause(exc)}")
    error.reason = cause(exc)
    return error


_ERRNO = re.compile(r"\[Errno (\d+)\][^:'\n]*(?::\s*'([^'\n]+)')?", re.IGNORECASE)  # [Errno 28] Why: 'file'?
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS, errno.EACCES, errno.EPERM})


def write_failure_in(exc: BaseException) -> OSError | None:
    """The write failure under `exc`, if that is what it is: an OSError with a write errno in `exc` or
    its causes, or a library's wrapper that only says "[Errno 28]" in its message (LeRobot's
    "Encoder thread for ... failed: [Errno 28] ...", pyarrow's "Error writing bytes to file")."""
    seen = 0
    while exc is not None and seen < 8:
        if isinstance(exc, WriteError):
            return exc
        if isinstance(exc, OSError) and exc.errno in WRITE_ERRNOS:
            return exc
        match = _ERRNO.search(str(exc))
        if match and int(match.group(1)) in WRITE_ERRNOS:
            number = int(match.group(1))
            return OSError(number, os.strerror(number), match.group(2) or getattr(exc, "filename", None))
        exc = exc.__cause__ or exc.__context__
        seen += 1
    return None


def write_bytes_whole(path: str | Path, data: bytes, shared: bool = False) -> Path:
    """Write `data` to `path` through `path.part` and a rename: a kill or a full disk never leaves a
    half file under the name; on an error the .part is removed and a WriteError raised.

    shared: other writers (threads, processes) may write the same file at once, so each writes a
    temporary file of its own (`<name>.<random>.part`, private to its owner as mkstemp makes it) and the
    last rename wins whole."""
    path = Path(path)
    tmp: Path | None = None
    try:
        if shared:
            fd, name = tempfile.mkstemp(dir=path.parent, prefix=path.name + ".", suffix=PART)
            tmp = Path(name)
            with os.fdopen(fd, "wb") as fh:
                fh.write(data)
        else:
            tmp = path.with_name(path.name + PART)
            tmp.write_bytes(data)
        os.replace(tmp, path)
    except OSError as exc:
        if tmp is not None:
            with contextlib.suppress(OSError):
                tmp.unlink()
        raise write_error(path, exc) from None
    return path


def write_text_whole(path: str | Path, text: str, shared: bool = False) -> Path:
    """`write_bytes_whole` for UTF-8 text."""
    return write_bytes_whole(path, text.encode("utf-8"), shared)


def remove_parts(directory: str | Path) -> list[Path]:
    """Delete the `*.part` files a killed writer left in `directory` (not below it); the ones removed."""
    directory = Path(directory)
    removed = []
    if directory.is_dir():
        for path in directory.glob("*" + PART):
            with contextlib.suppress(OSError):
                path.unlink()
                removed.append(path)
    return removed


def free_bytes(directory: str | Path) -> int:
    """Free bytes on the file system that holds `directory` (or its nearest existing parent)."""
    path = Path(directory).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def _size(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000.0
    return f"{n:.1f} TB"  # pragma: no cover


def check_free_space(directory: str | Path, need: float, what: str) -> None:
    """Raise NotEnoughSpace when the free space under `directory` is clearly below `need` bytes.

    what: the work it is for, e.g. "18 more episodes of ~135 KB".
    """
    free = free_bytes(directory)
    if free < SPACE_MARGIN * need:
        raise NotEnoughSpace(f"{directory}: not enough free space: {what} need about {_size(need)}, "
                             f"{_size(free)} free (free some space, or add --force to go on anyway)")


__all__ = ["NotEnoughSpace", "PART", "WriteError", "cause", "check_free_space", "free_bytes", "remove_parts",
           "write_bytes_whole", "write_error", "write_failure_in", "write_text_whole"]
