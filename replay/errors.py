"""Turning an exception from a library into the one line a user is shown (defined with the root error)."""

from scenes.errors import TeleopError, first_line

__all__ = ["TeleopError", "first_line"]
