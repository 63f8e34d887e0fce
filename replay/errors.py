"""Turning an exception from a library into the one line a user is shown."""

from __future__ import annotations


def first_line(exc: BaseException, default: str | None = None) -> str:
    """The first non-empty line of `exc`'s message, else `default`, else its type name."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else (default or type(exc).__name__)
