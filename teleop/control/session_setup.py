"""A Session with its recorder, and the devices that drive it: what `teleop run` and `teleop serve` share.

The command line turns its flags into these calls (teleop/cli/session_args.py); a script
may call them directly. Speeds are the hold-to-move rates: m/s and rad/s.
"""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path

from devices.base import Cautioned, Device
from devices.planned import Planner
from devices.registry import DeviceOptions, open_devices
from scenes.vary.variation import Variation
from teleop.control.recording import Recorder
from teleop.control.session import Session
from teleop.errors import UsageError


def check_record_dir(record: Path | None) -> None:
    """A record directory may exist, but not as a file."""
    if record is not None and record.exists() and not record.is_dir():
        raise UsageError(f"--record {record}: exists and is not a directory")


def open_session(
    scene: str,
    robot: str,
    seed: int,
    control_hz: float,
    variation: Variation | None = None,
    record: Path | None = None,
    formats: tuple[str, ...] = ("mcap",),
    verify: str = "sync",
    on_error: str = "raise",
) -> Session:
    """A Session, with a Recorder into `record` attached when a directory is given."""
    check_record_dir(record)
    session = Session(scene=scene, robot=robot, seed=seed, control_hz=control_hz, variation=variation)
    if record is not None:
        Recorder(session, record, formats, verify=verify, on_error=on_error)
    return session


def open_session_devices(
    spec: str,
    n_arms: int,
    pos_speed: float,
    rot_speed: float,
    serving: bool = False,
    log: Callable[[str], None] | None = None,
    planner: Callable[[str], Planner] | None = None,
) -> tuple[list[Device], list[str]]:
    """The devices of a comma list (one way for run and serve); problems and caveats go to `log`.

    Serving, a session may start with no device but the page (the gizmo comes and goes with
    browsers), and a misspelt device name is an error rather than a line in the device list.
    `planner` makes an instruct:SENTENCE's planner (teleop.instruct.session_plan.make_planner).
    """
    log = log or (lambda m: print(m, file=sys.stderr))
    if pos_speed <= 0 or rot_speed <= 0:
        raise UsageError("--pos-speed and --rot-speed must be positive")
    options = DeviceOptions(pos_speed=pos_speed, rot_speed=rot_speed, n_arms=n_arms, planner=planner)
    devices, problems = open_devices(spec, options, require_any=not serving, require_known=serving)
    for line in problems:
        log(f"device not started: {line}")
    for device in devices:
        if isinstance(device, Cautioned) and device.warning:
            log(f"{device.name}: {device.warning}")
    return devices, problems
