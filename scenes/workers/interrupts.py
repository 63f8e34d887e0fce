"""Work that a Ctrl-C must not cut in half, without touching signal handlers (those are the CLI's).

A library call gets Ctrl-C as a KeyboardInterrupt in the main thread, at any
bytecode. A step that must end whole (LeRobot's save_episode writes data, video
and metadata in turn; finalize writes the parquet footers; a merge; a save of the
episode in progress) runs in a thread of its own while the main thread waits:
an interrupt then lands in the wait, is remembered, and the step goes on.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import TypeVar

T = TypeVar("T")


def shielded(fn: Callable[[], T]) -> tuple[T, bool]:
    """(fn(), whether a Ctrl-C came while it ran); fn runs to its end either way.

    An exception fn raises is raised here. Off the main thread (where no interrupt
    arrives) fn simply runs.
    """
    if threading.current_thread() is not threading.main_thread():
        return fn(), False
    done = threading.Event()
    box: dict[str, object] = {}

    def target() -> None:
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            box["error"] = exc
        finally:
            done.set()

    interrupted = False
    worker = threading.Thread(target=target, name="shielded", daemon=False)
    worker.start()
    while True:
        try:
            done.wait()
            break
        except KeyboardInterrupt:
            interrupted = True
    worker.join()
    if "error" in box:
        raise box["error"]  # type: ignore[misc]
    return box["value"], interrupted  # type: ignore[return-value]


def is_cancelled(cancel: threading.Event | None) -> bool:
    """Whether a cancellation token (set by the CLI's Ctrl-C handler, or a driver) is set; None never is."""
    return cancel is not None and cancel.is_set()
