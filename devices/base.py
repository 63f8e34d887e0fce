"""The device contract: anything that turns a person's (or a script's) intent into Commands.

Every device implements `Device` (start / poll / close). What only some devices
can do is a capability, declared below as its own `Protocol` and checked with
`isinstance` (they are runtime-checkable), so a loop asks "can this device be
restarted?" by type rather than by probing attribute names.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from devices.command import Command
from devices.view import SessionView
from scenes.errors import TeleopError


class DeviceError(TeleopError):
    """A device could not start or run; the message is one line a user can act on."""


@runtime_checkable
class Device(Protocol):
    """An input device polled once per control tick.

    `start` opens the device and raises DeviceError with a one-line reason if it
    cannot. `poll` returns the commands for this tick (deltas already scaled by
    `dt` seconds, so a held key moves at a set speed whatever the control rate).
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


@runtime_checkable
class Restartable(Protocol):
    """A device that plays something from its beginning again at each new episode (a script)."""

    def restart(self) -> None: ...


@runtime_checkable
class SceneChecked(Protocol):
    """A device whose input names parts of the scene (a script's bodies): checked against it before the
    first tick, so a wrong name is one error before anything runs or is recorded, not one mid-episode."""

    def check(self, view: SessionView) -> None:
        """Raise a TeleopError (one line naming the input and the name) if the scene lacks what it names."""
        ...


@runtime_checkable
class SpeedControlled(Protocol):
    """A hold-to-move device: full deflection moves the target at these speeds."""

    pos_speed: float  # m/s
    rot_speed: float  # rad/s


@runtime_checkable
class InputStamped(Protocol):
    """A device that stamps its newest input, so a page can show input-to-display latency."""

    last_input_time: float  # time.monotonic() when the newest input handed to the loop arrived


@runtime_checkable
class Cautioned(Protocol):
    """A device that started but with a caveat the user should read (a keyboard under Wayland)."""

    warning: str  # "" when there is nothing to say
