"""Ctrl-C and SIGTERM are the command line's: the only place that installs signal handlers.

Library calls take a cancellation token (a threading.Event) and stop at their next
safe point once it is set (an episode whole, a dataset finalized, the workers'
finished results kept), or end on a KeyboardInterrupt the way a script's Ctrl-C
gives it. A command picks how a signal reaches what it runs:
- `cancel_on_interrupt()`: the signal sets a token handed to the call (export,
  generate, serve, the replay viewer). A second Ctrl-C raises KeyboardInterrupt, for
  a step that does not look at the token (an import of seconds); the steps that must
  end whole hold it until they have (scenes.workers.shielded).
- `interrupts_ignored()`: around a save that a second Ctrl-C must not cut short
  (`teleop run`, whose loop ends on the KeyboardInterrupt itself).
- `terminate_as_interrupt()`: SIGTERM ends any command the way Ctrl-C does.
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def terminate_as_interrupt() -> None:
    """SIGTERM raises KeyboardInterrupt in the main thread, as Ctrl-C does (an episode in progress is kept)."""
    signal.signal(signal.SIGTERM, _raise_interrupt)


@contextlib.contextmanager
def cancel_on_interrupt(even_if_ignored: bool = False) -> Iterator[threading.Event]:
    """While the block runs, SIGINT and SIGTERM set the token it gets instead of raising.

    A command started with SIGINT ignored (`nohup ... &`: the shell keeps a terminal's
    Ctrl-C from background jobs) keeps ignoring it unless `even_if_ignored` (a server,
    stopped with SIGINT by whoever started it). The handlers before are restored after.
    """
    token = threading.Event()

    def handler(signum, frame) -> None:
        if signum == signal.SIGINT and token.is_set():
            raise KeyboardInterrupt  # asked twice: stop now, wherever this is
        token.set()

    signals = [signal.SIGTERM]
    if even_if_ignored or signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signals.append(signal.SIGINT)
    previous = {sig: signal.signal(sig, handler) for sig in signals}
    try:
        yield token
    finally:
        for sig, old in previous.items():
            signal.signal(sig, signal.SIG_DFL if old is None else old)  # None: a handler set outside Python


@contextlib.contextmanager
def interrupts_ignored() -> Iterator[None]:
    """Ctrl-C is ignored while the block runs (a save that must end whole); the handler before comes back after."""
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.SIG_DFL if previous is None else previous)
