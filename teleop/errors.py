"""Errors that reach the user as one line and exit code 2."""


class UsageError(Exception):
    """Bad input from the user: a file, a flag, a script. The message is the whole story."""
