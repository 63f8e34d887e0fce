"""The one root of every error a user can cause, and how one reaches them as a line.

It lives at the bottom of the import graph (scenes imports none of our other
folders) so that every layer can subclass it: scenes, devices, recorder, replay
and the app. The command line turns any `TeleopError` into its first line and
exit code 2; anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class TeleopError(Exception):
    """Something the user can fix (a file, an argument, a device, the disk); the message is one line."""


def first_line(exc: BaseException, default: str | None = None) -> str:
    """The first non-empty line of `exc`'s message, else `default`, else its type name."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else (default or type(exc).__name__)
