"""Connecting a LeRobot arm, the one way both a leader and a follower connect (issue 56 item 3).

A leader (devices/leader_connect.py, LeRobot's teleoperator classes) and a follower (teleop/control/follower.py,
LeRobot's `SOFollower`) are connected the same way, each step with one rule:

1. the calibration file is there (LeRobot's `calibrate()` would otherwise wait on stdin);
2. before LeRobot's own connect, which energises a follower: the port is opened without LeRobot's handshake,
   each servo is pinged (PING_TRIES times, and until PING_PATIENCE_S from the first ping, shared by the bus:
   a reply missed by a loaded host or USB adapter is not a missing servo), its model compared, and the
   calibration in the file compared with the servos' registers: a mismatch is said only when CALIBRATION_READS
   reads in a row find it (a read garbled on a busy bus differs once, a wrong calibration every time);
3. LeRobot's `connect(calibrate=False)`, tried CONNECT_TRIES times and for CONNECT_PATIENCE_S (the servos
   answered the pings just before: a failure here is a late reply, not a missing arm).

Every fault is one line (ArmError) that starts with the arm's name. Whatever ends a connect early (a fault,
Ctrl-C, SIGTERM raised as KeyboardInterrupt) releases the arm first: a follower's torque off, as far as its
servos answer, and the port closed (`release`), with a second Ctrl-C held until that is done.
LeRobot is never imported here: the caller makes its device object. Imported when an arm connects (its
`shielded` brings the worker pool's package), not when the command line starts.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from devices.base import DeviceError
from devices.serial_ports import DIALOUT_HINT
from scenes.errors import first_line
from scenes.workers.interrupts import shielded

PING_TRIES = 3  # a servo that answers none of this many pings, nor any until the bus's patience is out, is missing
PING_PATIENCE_S = 5.0  # seconds from the first ping (one waits ~35 ms for its answer, which a host loaded to many times its
# cores misses for seconds: measured here, servo 1 unanswered for 3 s); a port with no servo costs it once
CALIBRATION_READS = 3  # reads of the servos' calibration registers that must all differ from the file to refuse it
CONNECT_TRIES = 3  # LeRobot's connect (its handshake, then configuration writes), tried at least this often
CONNECT_PATIENCE_S = 5.0  # and for at least this long from the first try
READ_PATIENCE_S = 2.0  # one read (the calibration registers, the first positions) asked again for this long
TORQUE_OFF_TRIES = 3  # writes of Torque_Enable 0 to each servo on release, at least (one not answered is asked again)
TORQUE_OFF_PATIENCE_S = 1.0  # and until this long from the first: a bus that hiccups as the session ends still hears it


class ArmError(DeviceError):
    """A LeRobot arm that cannot be connected: one line, starting with the arm's name."""


@dataclass(frozen=True)
class ArmWords:
    """How the messages name an arm: "{where}: ..." and what it should have been."""

    where: str  # the start of every message ("so101_leader:/dev/ttyACM0", "/dev/ttyACM1")
    what: str  # "the leader", "the follower"
    model_of: str  # what a wrong model is asked to be ("an SO-101 follower")
    calibrate: str  # the `lerobot-calibrate ...` command that writes the calibration file


def patiently(read: Callable[[], Any], patience_s: float = READ_PATIENCE_S) -> Any:
    """`read()`, asked again for up to `patience_s` while it raises (a reply late on a loaded host); then its error."""
    give_up = time.monotonic() + patience_s
    while True:
        try:
            return read()
        except Exception:  # noqa: BLE001 - LeRobot raises ConnectionError, the Feetech SDK IndexError on a short packet
            if time.monotonic() >= give_up:
                raise
            time.sleep(0.05)


def ping(bus: Any, motor: str, give_up: float) -> int | None:
    """A servo's model number, or None if it answers none of PING_TRIES pings nor any more until `give_up`
    (time.monotonic()); a garbled answer is asked again."""
    tries = 0
    while True:
        try:
            model = bus.ping(motor)
        except Exception:  # noqa: BLE001 - a short status packet (IndexError) or a port that failed
            model = None
        tries += 1
        if model is not None:
            return model
        if tries >= PING_TRIES and time.monotonic() >= give_up:
            return None
        time.sleep(0.01)  # a port that fails at once is not asked in a busy loop


def servo_problem(bus: Any, words: ArmWords, patience_s: float = PING_PATIENCE_S) -> str | None:
    """What the pings found wrong, in one line (servos silent, or of the wrong model), or None.

    The bus's port must be open. With no patience (a quick try every second while unplugged) the first silent
    servo ends the pings."""
    give_up = time.monotonic() + patience_s
    found: dict[str, int | None] = {}
    for name in bus.motors:
        found[name] = ping(bus, name, give_up)
        if found[name] is None and patience_s <= 0:
            break
    silent = [name for name, model in found.items() if model is None]
    if silent and len(silent) == len(found):
        return f"{words.where}: no servo answered (ids 1-{len(bus.motors)}): is {words.what} powered and on this port?"
    if silent:
        ids = ", ".join(f"{bus.motors[n].id} ({n})" for n in silent)
        return f"{words.where}: servo {ids} did not answer: check {'its cable' if len(silent) == 1 else 'their cables'}"
    for name, model in found.items():
        motor = bus.motors[name]
        expected = bus.model_number_table[motor.model]
        if model != expected:
            return (f"{words.where}: wrong servo model: servo {motor.id} ({name}) is model {model}, not an "
                    f"{motor.model.upper()} ({expected}): is this {words.model_of}?")
    return None


def calibration_matches(device: Any) -> bool:
    """Whether the servos' calibration registers match the file, by one rule: refused only when every one of
    CALIBRATION_READS reads differs; a read that fails is asked again (`patiently`), then raises."""
    for k in range(CALIBRATION_READS):
        if k:
            time.sleep(0.05)
        if patiently(lambda: device.is_calibrated):
            return True
    return False


def port_error(words: ArmWords, exc: BaseException) -> ArmError:
    """One line for a port LeRobot could not open (its own message is several lines)."""
    cause = exc.__cause__ or exc.__context__ or exc
    if isinstance(cause, PermissionError) or "ermission denied" in str(cause):
        return ArmError(f"{words.where}: {DIALOUT_HINT}")
    return ArmError(f"{words.where}: cannot open the port ({first_line(cause)})")


def check_arm(device: Any, words: ArmWords, patient: bool = True) -> None:
    """Steps 1-2 of the module docstring, nothing energised: the port is closed again after; ArmError otherwise."""
    path = Path(device.calibration_fpath)
    if not path.is_file():
        raise ArmError(f"{words.where}: no calibration file {path}; calibrate {words.what}: {words.calibrate}")
    bus = device.bus
    try:
        bus.connect(handshake=False)
    except Exception as exc:  # noqa: BLE001 - LeRobot's several lines become one
        raise port_error(words, exc) from None
    try:
        problem = servo_problem(bus, words, PING_PATIENCE_S if patient else 0.0)
        if problem:
            raise ArmError(problem)
        try:
            calibrated = calibration_matches(device)
        except Exception as exc:  # noqa: BLE001 - it answered the pings, then stopped
            raise ArmError(f"{words.where}: the servos stopped answering while their calibration was read "
                           f"({first_line(exc)})") from None
        if not calibrated:
            raise ArmError(f"{words.where}: the calibration in {path} does not match the servos; "
                           f"calibrate again: {words.calibrate}")
    finally:
        release(device, torque_off=False)  # nothing was enabled yet


def connect_arm(device: Any, words: ArmWords, energises: bool, patient: bool = True) -> None:
    """Connect a LeRobot teleoperator or robot (made, not connected) the one way of the module docstring.

    `energises`: LeRobot's connect enables torque (a follower): every way out of this call but a normal return
    disables it again. `patient` False (a reconnect tried every second): one try, pings without patience.
    """
    check_arm(device, words, patient)
    tries = CONNECT_TRIES if patient else 1
    give_up = time.monotonic() + (CONNECT_PATIENCE_S if patient else 0.0)
    attempt = 0
    try:
        while True:
            attempt += 1
            try:
                device.connect(calibrate=False)  # LeRobot's calibrate() would wait on stdin: never called
                return
            except Exception as exc:  # noqa: BLE001 - LeRobot's several lines become one
                release(device, torque_off=energises)  # it may have enabled torque before it failed
                if attempt >= tries and time.monotonic() >= give_up:
                    raise _connect_error(words, exc) from None
                time.sleep(0.1)
    except ArmError:
        raise  # released above
    except BaseException:  # Ctrl-C or SIGTERM mid-connect: torque off before anything else
        shielded(lambda: release(device, torque_off=energises))
        raise


def _connect_error(words: ArmWords, exc: BaseException) -> ArmError:
    cause = exc.__cause__ or exc
    if isinstance(cause, OSError) and not isinstance(cause, ConnectionError):  # the port itself (permission, gone)
        return port_error(words, exc)
    return ArmError(f"{words.where}: cannot talk to the servos ({first_line(cause)})")


def release(device: Any, torque_off: bool) -> None:
    """Close the arm's port; with `torque_off` first disable every servo's torque, as far as each answers.

    Torque is written off servo by servo (each TORQUE_OFF_TRIES times, and until TORQUE_OFF_PATIENCE_S from the
    first write, shared by the bus), so a reply lost on a busy bus does not leave a servo on and one that does not
    answer does not keep the others on; a port closed underneath (a reconnect that failed half-way) is opened
    again to say it. Never raises an Exception: an arm that is gone cannot be told.
    """
    bus = getattr(device, "bus", None)
    if bus is None:
        return
    try:
        if torque_off:
            if not bus.is_connected:
                bus.connect(handshake=False)
            # A transfer cut short (Ctrl-C mid-read) leaves the SDK's port marked busy and bytes unread: every
            # write would then fail at once, as LeRobot's own disconnect knows
            bus.port_handler.clearPort()
            bus.port_handler.is_using = False
            give_up = time.monotonic() + TORQUE_OFF_PATIENCE_S
            for motor in bus.motors:
                tries = 0
                while True:
                    try:
                        bus.disable_torque(motor)
                        break
                    except Exception:  # noqa: BLE001 - not answered: again, then on to the next servo
                        tries += 1
                        if tries >= TORQUE_OFF_TRIES and time.monotonic() >= give_up:
                            break
                        time.sleep(0.01)
    except Exception:  # noqa: BLE001 - a port that cannot be opened again: nothing reaches the arm
        pass
    try:
        if bus.is_connected:
            bus.port_handler.closePort()
    except Exception:  # noqa: BLE001 - closing a port that went away
        pass
