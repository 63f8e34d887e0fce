"""Keep a `--json` command's stdout to its one JSON object.

While a `--json` command runs, everything else that would reach stdout goes to
stderr instead: Python writes (print, rich consoles such as viser's banner, even
ones holding the old sys.stdout), and writes to file descriptor 1 (C libraries,
child processes that inherit it). Only `print_json` reaches the real stdout.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections.abc import Iterator
from typing import IO, Any

_real: IO[str] | None = None  # the real stdout while a --json command runs
_printed = 0


def _writes_fd1(stream: IO[str]) -> bool:
    try:
        return stream.fileno() == 1
    except (AttributeError, OSError, ValueError):  # a capture buffer (pytest's capsys, StringIO)
        return False


@contextlib.contextmanager
def json_stdout() -> Iterator[None]:
    """Point stdout (sys.stdout and fd 1) at stderr until the block ends; `print_json` still reaches stdout."""
    global _real, _printed
    original = sys.stdout
    for stream in (original, sys.__stdout__, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()
    saved_fd = os.dup(1)
    # The JSON goes where stdout went: fd 1 as it was, or the caller's own stream when
    # sys.stdout is not fd 1 (then the fd redirection does not affect it).
    real = os.fdopen(os.dup(saved_fd), "w", encoding="utf-8") if _writes_fd1(original) else original
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    _real, _printed = real, 0
    try:
        yield
    finally:
        for stream in (sys.stdout, sys.__stdout__, sys.stderr):
            with contextlib.suppress(Exception):
                stream.flush()
        os.dup2(saved_fd, 1)
        os.close(saved_fd)
        sys.stdout = original
        _real = None
        if real is not original:
            real.close()


def print_json(obj: Any, indent: int | None = None) -> None:
    """Print the command's JSON value: on the real stdout, once per `--json` command."""
    global _printed
    text = json.dumps(obj, indent=indent) + "\n"
    if _real is None:
        sys.stdout.write(text)
        sys.stdout.flush()
        return
    if _printed:
        raise RuntimeError("a --json command printed a second JSON value")
    _printed += 1
    _real.write(text)
    _real.flush()
