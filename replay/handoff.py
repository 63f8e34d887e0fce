"""Handing items between threads that may be told to stop: a render thread and its reader.

A producer blocked on a full queue would wait forever once its reader has gone; these
wait in short turns and give up as soon as `stop` is set.
"""

from __future__ import annotations

import queue
import threading


def put_unless(out: queue.Queue, item, stop: threading.Event) -> bool:
    """Queue an item unless `stop` is set first; False: stop producing."""
    while not stop.is_set():
        try:
            out.put(item, timeout=0.1)
            return True
        except queue.Full:
            continue
    return False


def get_unless(source: queue.Queue, stop: threading.Event):
    """The next item, or None once `stop` is set."""
    while not stop.is_set():
        try:
            return source.get(timeout=0.1)
        except queue.Empty:
            continue
    return None
