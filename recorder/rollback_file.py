"""A file for h5py's `fileobj` driver that HDF5 never sees fail, and that can go back to its last commit.

HDF5 does not survive a failed write (a full disk, a file size limit, an I/O
error): a flush that fails half way leaves its metadata half rewritten, so the
file no longer opens ("addr overflow"), and the open handle can then neither
flush nor close, so h5py's finalizers print tracebacks and the library crashes
the interpreter at exit (measured with h5py 3.16 / HDF5 2.0: exit 139).

So writes go through this file instead of HDF5's own driver. The first OSError
is kept in `error` and HDF5 is told the write succeeded; from then on writes and
resizes are kept in memory only (reads see them), so HDF5 stays consistent and
closes cleanly. `rollback` then puts back the bytes the file had at the last
`commit` (the owner commits right after a successful HDF5 flush, when the file
on disk is a whole, readable HDF5 file) from an undo log of the bytes each write
since then overwrote, and cuts the file back to that size. Undoing needs no new
disk space: it rewrites bytes in place and shrinks the file.
"""

from __future__ import annotations

import os
from pathlib import Path


class RollbackFile:
    """A new file at `path` (FileExistsError if there is one), read and written at byte offsets."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0), 0o666)
        self._pos = 0
        self._size = 0  # bytes on disk
        self._base = 0  # size at the last commit
        self._undo: list[tuple[int, bytes]] = []  # (offset, bytes it held before) since the last commit
        self._after: list[tuple[int, bytes | None]] = []  # after a failure: (offset, data) writes, (size, None) resizes
        self._vsize = 0  # the size HDF5 believes, after a failure
        self.error: OSError | None = None  # the first write error

    def __repr__(self) -> str:  # h5py names the HDF5 file after this
        return f"RollbackFile({str(self.path)!r})"

    # -- what h5py's fileobj driver calls ----------------------------------------
    def seek(self, offset: int, whence: int = os.SEEK_SET) -> int:
        end = self._vsize if self.error is not None else self._size
        self._pos = offset if whence == os.SEEK_SET else (self._pos + offset if whence == os.SEEK_CUR else end + offset)
        return self._pos

    def tell(self) -> int:
        return self._pos

    def readinto(self, buf) -> int:
        """Bytes at the position; past the end reads as zeros (as HDF5's own driver does)."""
        view = memoryview(buf).cast("B")
        n, pos = len(view), self._pos
        got = os.preadv(self._fd, [view], pos) if n else 0
        if got < n:
            view[got:] = bytes(n - got)
        if self.error is not None:
            self._overlay(view, pos)
        self._pos = pos + n
        return n

    def read(self, size: int = -1) -> bytes:
        if size is None or size < 0:
            size = max(0, (self._vsize if self.error is not None else self._size) - self._pos)
        buf = bytearray(size)
        self.readinto(buf)
        return bytes(buf)

    def write(self, data) -> int:
        view = memoryview(data).cast("B")
        n, pos = len(view), self._pos
        self._pos = pos + n
        if self.error is not None:
            self._after.append((pos, bytes(view)))
            self._vsize = max(self._vsize, pos + n)
            return n
        if pos < self._base:
            self._save(pos, min(pos + n, self._base))
        done = 0
        try:
            while done < n:
                done += os.pwrite(self._fd, view[done:], pos + done)
        except OSError as exc:
            self._fail(exc)
            self._after.append((pos, bytes(view)))  # HDF5 goes on as if all of it was written
            self._vsize = max(self._vsize, pos + n)
            return n
        self._size = max(self._size, pos + n)
        return n

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else size
        if self.error is not None:
            self._after.append((size, None))
            self._vsize = size
            return size
        if size < self._size and size < self._base:
            self._save(size, min(self._size, self._base))
        try:
            os.ftruncate(self._fd, size)
        except OSError as exc:  # growing past a file size limit
            self._fail(exc)
            self._after.append((size, None))
            self._vsize = size
            return size
        self._size = size
        return size

    def flush(self) -> None:
        """Nothing to do: every write already went to the OS (it survives the process being killed)."""

    # -- commit / rollback ---------------------------------------------------------
    def commit(self) -> None:
        """The bytes on disk are a state to come back to (call after a successful HDF5 flush, never after a failure)."""
        if self.error is None:
            self._base = self._size
            self._undo.clear()

    def rollback(self) -> None:
        """After a failure, put back the bytes of the last commit and cut the file to its size (best effort)."""
        if self.error is None or self._fd < 0:
            return
        try:
            for offset, old in reversed(self._undo):
                os.pwrite(self._fd, old, offset)
            os.ftruncate(self._fd, self._base)
        except OSError:
            pass  # nothing more can be done: the file stays as the failure left it
        self._undo.clear()
        self._size = self._base

    def close(self) -> None:
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            os.close(fd)

    @property
    def closed(self) -> bool:
        return self._fd < 0

    # -- internals -----------------------------------------------------------------
    def _save(self, start: int, stop: int) -> None:
        """Keep the bytes in [start, stop) as they are now (the region below the committed size only)."""
        if stop > start:
            self._undo.append((start, os.pread(self._fd, stop - start, start)))

    def _fail(self, exc: OSError) -> None:
        self.error = exc
        self._vsize = max(self._size, self._pos)

    def _overlay(self, view: memoryview, pos: int) -> None:
        """Apply what HDF5 wrote after the failure (kept in memory) to bytes read from disk at `pos`."""
        end = pos + len(view)
        for offset, data in self._after:
            if data is None:  # a resize: bytes past it read as zeros
                if offset < end:
                    lo = max(offset, pos)
                    view[lo - pos :] = bytes(end - lo)
                continue
            lo, hi = max(offset, pos), min(offset + len(data), end)
            if lo < hi:
                view[lo - pos : hi - pos] = data[lo - offset : hi - offset]
