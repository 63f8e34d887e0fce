"""The device contract: anything that turns a person's (or a script's) intent into Commands."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from teleop.command import Command
from teleop.view import SessionView


class DeviceError(Exception):
    """A device could not start or run; the message is one line a user can act on."""


@runtime_checkable
class Device(Protocol):
    """An input device polled once per control tick.

    `start` opens the device and raises DeviceError with a one-line reason if it
    cannot. `poll` returns the commands for this tick (deltas already scaled by
    `dt`, so a held key moves at a set speed whatever the control rate).
    """

    name: str
    kind: str

    def start(self) -> None: ...

    def poll(self, view: SessionView, dt: float) -> list[Command]: ...

    def status(self) -> str:
        """A short word for the panel: "connected", "disconnected", "done", ..."""
        ...

    @property
    def finished(self) -> bool:
        """True when the device has nothing more to say (a script that ran out)."""
        ...

    def close(self) -> None: ...
