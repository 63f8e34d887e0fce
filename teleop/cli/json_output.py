"""Keep a `--json` command's stdout to its one JSON object.

While a `--json` command runs, everything else that would reach stdout goes to
stderr instead: Python writes (print, rich consoles such as viser's banner, even
ones holding the old sys.stdout), and writes to file descriptor 1 (C libraries,
child processes that inherit it). Only `print_json` reaches the real stdout.

`json_command` is the one place that makes a `--json` command answer whatever
happens: a command that ends without printing its object (an error the user can
fix, Ctrl-C, a bug) prints `{"error": "<one line>"}` instead, so stdout always
holds exactly one JSON object.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
from collections.abc import Iterator
from typing import IO, Any

from scenes.errors import TeleopError, first_line

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


@contextlib.contextmanager
def json_command(command: str) -> Iterator[None]:
    """Run a `--json` command's block: stdout kept to one object, `{"error": ...}` when it printed none.

    The exception (or exit) goes on as it would without --json: the entry point still
    prints its one line on stderr and picks the exit code.
    """
    with json_stdout():
        try:
            yield
        except BrokenPipeError:  # the reader left: nothing more can reach it
            raise
        except BaseException as exc:
            if not json_printed():
                print_json({"error": error_text(exc)})
            raise
        if not json_printed():
            print_json({"error": f"teleop {command} ended without a result"})


def error_text(exc: BaseException) -> str:
    """What `{"error": ...}` says of an exception: a user error's one line, an interrupt, or a bug's type."""
    if isinstance(exc, TeleopError):
        return first_line(exc)
    if isinstance(exc, KeyboardInterrupt):
        return "interrupted"
    return f"internal error: {type(exc).__name__}" + (f": {first_line(exc)}" if str(exc).strip() else "")


def json_printed() -> bool:
    """Whether the `--json` command now running (or the last one) has printed its JSON value."""
    return _printed > 0


def print_json(obj: Any, indent: int | None = None) -> None:
    """Print the command's JSON value: on the real stdout, once per `--json` command."""
    global _printed
    text = json.dumps(obj, indent=indent) + "\n"
    if _real is None:
        sys.stdout.write(text)
        sys.stdout.flush()
        _printed += 1
        return
    if _printed:
        raise RuntimeError("a --json command printed a second JSON value")
    _printed += 1
    _real.write(text)
    _real.flush()
