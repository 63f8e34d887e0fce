"""Errors that reach the user as one line and exit code 2 (all are `TeleopError`s)."""

from scenes.errors import TeleopError


class SessionError(TeleopError, ValueError):
    """A session cannot be set up as asked (a control rate out of range, a recorder already attached)."""


class UsageError(TeleopError):
    """Bad command-line input: a flag, a file, a script. The message is the whole story."""


class EnvError(TeleopError, ValueError):
    """A Gymnasium environment cannot be made or driven as asked (action mode, cameras, image size, an action)."""
