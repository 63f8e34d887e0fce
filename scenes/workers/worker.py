"""Inside a local worker process: never outlive the driver, take Ctrl-C from the driver only.

A worker is forked from multiprocessing's fork server (runner.worker_context), never
from the driver: a GL context or MuJoCo state does not survive a fork. As it starts it
- leaves the terminal's process group: a terminal's Ctrl-C goes to the driver,
  which decides what the workers do (stop now, or end their task early);
- starts a daemon thread that waits on the driver (a pidfd: the driver is not its
  parent) and exits the process at once when the driver ends, even by SIGKILL. The
  fork server sees the driver's end of its pipe close and exits too, and with them
  gone multiprocessing's resource tracker, whose pipe they held, exits as well;
- copies the driver's cancel request (a multiprocessing Event) into a
  threading.Event that the task hands to library code (`cancel_token()`).
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
from collections.abc import Callable
from typing import Any

POLL_S = 0.2  # how often the watch looks at the parent and the cancel request (s)

_cancel = threading.Event()
_shared: Any = None


class Marker:
    """Stands in a task's arguments for something the worker has of its own (replaced there by `call`)."""

    def __init__(self, name: str) -> None:
        self.name = name

    def __reduce__(self) -> str:
        return self.name  # unpickles as this module's object of that name, so `is` finds it


SHARED = Marker("SHARED")  # the object the runner sent each worker once
CANCEL = Marker("CANCEL")  # the worker's cancel_token()


def cancel_token() -> threading.Event:
    """Set once the driver asks the running tasks to end early (they keep what is whole)."""
    return _cancel


def start(parent: int, cancel: Any, shared: Any, setup: Callable[..., None] | None, setup_args: tuple) -> None:
    """ProcessPoolExecutor's initializer: the watch, the shared object, then the caller's own setup."""
    global _shared
    with contextlib.suppress(OSError):
        os.setpgid(0, 0)  # a process group of its own: a terminal's Ctrl-C reaches the driver only
    threading.Thread(target=_watch, args=(parent, cancel), name="watch-driver", daemon=True).start()
    _shared = shared
    if setup is not None:
        setup(*setup_args)


def _watch(parent: int, cancel: Any) -> None:
    driver_ended = _driver_watch(parent)
    while True:
        if driver_ended(POLL_S):
            os._exit(1)  # the driver is gone: nobody will take this worker's results
        if not _cancel.is_set():
            try:
                if cancel.is_set():
                    _cancel.set()
            except (OSError, EOFError):
                os._exit(1)


def _driver_watch(parent: int) -> Callable[[float], bool]:
    """A wait of up to `timeout` s that says whether the process `parent` has ended: a pidfd on Linux
    (readable once it exits, zombie or not), else a probe of the pid after the wait."""
    try:
        fd = os.pidfd_open(parent)
    except ProcessLookupError:
        return lambda timeout: True
    except (AttributeError, OSError):  # no pidfd here (not Linux, or a kernel before 5.3)
        def probe(timeout: float) -> bool:
            time.sleep(timeout)
            try:
                os.kill(parent, 0)
            except ProcessLookupError:
                return True
            except PermissionError:
                pass
            return False

        return probe
    return lambda timeout: bool(select.select([fd], [], [], timeout)[0])


def call(fn: Callable[..., Any], args: tuple) -> Any:
    """Run one task: fn(*args), with SHARED and CANCEL replaced by what they stand for here."""
    return fn(*[_shared if a is SHARED else _cancel if a is CANCEL else a for a in args])


def ready(pause_s: float) -> int:
    """A no-op task each worker takes once at start-up; the pause keeps one worker from taking two."""
    time.sleep(pause_s)
    return os.getpid()
