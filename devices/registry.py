"""Turn a `--device` string ("keyboard,spacemouse,script:demo.json") into started devices.

Spec words:
  keyboard                      the keyboard (pynput, X11 / macOS / Windows)
  spacemouse                    every SpaceMouse found, one per arm in turn
  spacemouse:N[:OPTION...]      the N-th SpaceMouse (`teleop devices` lists them);
                                OPTION: behind|facing (stance), toggle|hold (gripper),
                                arm=K, right=ACTION, sensitivity=F, deadzone=F
  script:FILE                   commands replayed from a JSON file
  instruct:SENTENCE             a plan made from a sentence when each episode begins (the app's planner,
                                devices/planned.py); the sentence runs to the end of the list, commas and all
  gizmo                         the browser's transform gizmo
  so101_leader:PORT[:OPTION...] a LeRobot leader arm (also so100_leader, koch_leader); OPTION:
                                id=NAME, calibration=DIR, map=FILE, scale=F, arm=K (values keep
                                their case; PORT may hold ':'). One that cannot start stops the
                                command (devices/lerobot_leader.py)
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from devices.base import Device, DeviceError
from devices.leader_connect import LeaderError

if TYPE_CHECKING:  # the planned device needs MuJoCo; `teleop --help` must not
    from devices.planned import Planner


@dataclass
class DeviceOptions:
    """Settings shared by the devices a session opens (`teleop run` flags)."""

    pos_speed: float = 0.15  # m/s for hold-to-move devices at full deflection
    rot_speed: float = 0.8  # rad/s
    n_arms: int = 1
    stance: str = "behind"  # SpaceMouse axis mapping: "behind" the robot or "facing" it
    gripper_mode: str = "toggle"  # SpaceMouse left button: "toggle" or "hold"
    right_button: str = "reset"  # SpaceMouse right button: none|gripper|frame|reset|start|save|discard
    sensitivity: float = 1.0  # SpaceMouse: multiplies both speeds
    deadzone: float = 0.03  # SpaceMouse: fraction of full deflection read as zero
    planner: "Callable[[str], Planner] | None" = None  # instruct:SENTENCE -> its planner (the app makes it; None: no instruct)


def make_device(spec: str, options: DeviceOptions) -> Device:
    """Build one device from its spec word; raises DeviceError for unknown words."""
    name, _, arg = spec.partition(":")
    name = name.strip().lower()
    if name in LEADER_DEVICES:
        from devices.lerobot_leader import make_leader  # its kinematics need MuJoCo; LeRobot loads when it starts

        return make_leader(name, arg, options.n_arms)  # case-preserving options, PORT may hold ':'
    if name == "script":
        from devices.script import ScriptDevice

        if not arg:
            raise DeviceError("the script device needs a file: script:FILE.json")
        return ScriptDevice(arg)
    if name == "instruct":
        from devices.planned import PlannedDevice

        sentence = arg.strip().strip('"').strip()
        if not sentence:
            raise DeviceError('the instruct device needs a sentence: instruct:"put the red cube on the blue cube"')
        if options.planner is None:
            raise DeviceError("instruct: no planner here (teleop run and teleop serve make one)")
        return PlannedDevice(sentence, options.planner(sentence))
    if name == "keyboard":
        from devices.keyboard import KeyboardDevice

        if arg:
            raise DeviceError(f"keyboard takes no options (got {spec!r})")
        return KeyboardDevice(pos_speed=options.pos_speed, rot_speed=options.rot_speed, n_arms=options.n_arms)
    if name == "spacemouse":
        return _spacemouse(arg, options)
    if name == "gizmo":
        from devices.gizmo import GizmoDevice

        if arg:
            raise DeviceError(f"gizmo takes no options (got {spec!r})")
        return GizmoDevice(n_arms=options.n_arms)
    if name in BROWSER_DEVICES:
        return _browser_device(name, arg, options)
    raise DeviceError(f"unknown device {spec!r} (known: {KNOWN_TEXT})")


def _browser_device(name: str, arg: str, options: DeviceOptions) -> Device:
    """A device the operator's browser feeds (teleop serve): gamepad[:arm=K], phone[:arm=K], webhid[:arm=K]."""
    arm = 0
    for token in (t.strip().lower() for t in arg.split(":") if t.strip()):
        key, _, value = token.partition("=")
        if key != "arm" or not value.isdigit() or int(value) >= max(options.n_arms, 1):
            raise DeviceError(f"{name}: unknown option {token!r} (use arm=K, K below {max(options.n_arms, 1)})")
        arm = int(value)
    suffix = f"-arm{arm}" if arm else ""
    if name == "gamepad":
        from devices.gamepad import GamepadDevice

        return GamepadDevice(name=f"gamepad{suffix}", arm=arm, pos_speed=options.pos_speed, rot_speed=options.rot_speed)
    if name == "phone":
        from devices.phone import PhoneDevice

        return PhoneDevice(name=f"phone{suffix}", arm=arm)
    from devices.webhid import WebHidSpaceMouse

    kw = spacemouse_options("", options)[1]
    return WebHidSpaceMouse(name=f"webhid-spacemouse{suffix}", arm=arm, **kw)


def spacemouse_options(arg: str, options: DeviceOptions) -> tuple[int | None, dict]:
    """Parse "N:facing:hold:arm=1:..." into (index or None, SpaceMouseDevice keyword arguments)."""
    index: int | None = None
    kw: dict = {
        "pos_speed": options.pos_speed,
        "rot_speed": options.rot_speed,
        "stance": options.stance,
        "gripper_mode": options.gripper_mode,
        "right_button": options.right_button,
        "sensitivity": options.sensitivity,
        "deadzone": options.deadzone,
    }
    for token in (t.strip().lower() for t in arg.split(":") if t.strip()):
        key, eq, value = token.partition("=")
        try:
            if not eq and key.isdigit():
                index = int(key)
            elif not eq and key in ("behind", "facing"):
                kw["stance"] = key
            elif not eq and key in ("toggle", "hold"):
                kw["gripper_mode"] = key
            elif key in ("stance", "right"):
                kw["stance" if key == "stance" else "right_button"] = value
            elif key == "gripper":
                kw["gripper_mode"] = value
            elif key == "arm":
                kw["arm"] = int(value)
            elif key in ("sensitivity", "deadzone"):
                kw[key] = float(value)
            else:
                raise ValueError
        except ValueError:
            raise DeviceError(
                f"bad SpaceMouse option {token!r} (use N, behind|facing, toggle|hold, arm=K, right=ACTION, "
                "sensitivity=F, deadzone=F)"
            ) from None
    return index, kw


def _spacemouse(arg: str, options: DeviceOptions) -> Device:
    from devices.spacemouse import SpaceMouseDevice, find_spacemice, open_hid, reopener

    index, kw = spacemouse_options(arg, options)
    found = find_spacemice()
    if not found:
        raise DeviceError(
            "no SpaceMouse found (no 3Dconnexion 6-DoF device on USB or a receiver); plug one in, "
            "and see `teleop devices`"
        )
    index = index or 0
    if index >= len(found):
        raise DeviceError(f"spacemouse:{index} does not exist: {len(found)} SpaceMouse found (spacemouse:0..{len(found) - 1})")
    info = found[index]
    kw.setdefault("arm", index % max(options.n_arms, 1))
    if not 0 <= kw["arm"] < max(options.n_arms, 1):
        raise DeviceError(f"spacemouse:{index}: arm={kw['arm']} but the scene has {options.n_arms} arm(s)")
    first_open = [True]
    again = reopener(info, index)

    def opener():
        if first_open[0]:
            first_open[0] = False
            return open_hid(info)
        return again()

    return SpaceMouseDevice(opener, name=f"spacemouse:{index}", **kw)


def _expand(word: str) -> list[str]:
    """A bare "spacemouse" means every SpaceMouse found (two of them drive the two arms)."""
    name, _, arg = word.partition(":")
    if name.strip().lower() != "spacemouse":
        return [word]
    try:
        index, _ = spacemouse_options(arg, DeviceOptions())
        if index is not None:
            return [word]
        from devices.spacemouse import find_spacemice

        count = len(find_spacemice())
    except DeviceError:
        return [word]  # make_device reports it
    if count <= 1:
        return [word]
    return [f"spacemouse:{i}" + (f":{arg}" if arg else "") for i in range(count)]


BROWSER_DEVICES = ("gamepad", "phone", "webhid")  # fed by the operator's browser (teleop serve)
LEADER_DEVICES = ("so101_leader", "so100_leader", "koch_leader")  # LeRobot leader arms on a serial port
KNOWN_DEVICES = ("keyboard", "spacemouse", "gizmo", "script", "instruct", *BROWSER_DEVICES, *LEADER_DEVICES)
KNOWN_TEXT = ("keyboard, spacemouse[:N], gizmo, script:FILE, instruct:SENTENCE, gamepad, phone, webhid, so101_leader:PORT, "
              "so100_leader:PORT, koch_leader:PORT")
# What a browser session opens unless told otherwise: the page's inputs, and this machine's keyboard and SpaceMouse.
SERVE_DEVICES = ("gizmo", "keyboard", "spacemouse", *BROWSER_DEVICES)


def split_spec(spec: str) -> list[str]:
    """The words of a comma list; an `instruct:` sentence runs to the end of it, commas and all."""
    m = re.search(r"(?:^|,)\s*instruct:", spec, re.IGNORECASE)
    head, tail = (spec[: m.start()], spec[m.start():].lstrip(",").strip()) if m else (spec, "")
    return [w.strip() for w in head.split(",") if w.strip()] + ([tail] if tail else [])


def open_devices(
    spec: str, options: DeviceOptions, require_any: bool = True, require_known: bool = False
) -> tuple[list[Device], list[str]]:
    """Start every device in a comma list: the one way `teleop run` and `teleop serve` open devices.

    Returns the devices that started and one line per device that did not,
    so that a session can carry on with the rest. A malformed script is an
    error (ScriptError); so is a list from which nothing started, when
    `require_any`, and a word naming no known device, when `require_known`
    (the browser session, where nothing else would tell the user). A started
    device may carry a caveat (`Cautioned`: a keyboard under Wayland) for the
    session to print. A leader arm that cannot start raises its LeaderError (the devices
    started before it are closed): a session must not run without the arm it was asked for.
    """
    started: list[Device] = []
    problems: list[str] = []
    words = split_spec(spec)
    if not words:
        raise DeviceError(f"no device given: name at least one of {', '.join(KNOWN_DEVICES)}")
    for word in words if require_known else ():
        if word.partition(":")[0].strip().lower() not in KNOWN_DEVICES:
            raise DeviceError(f"unknown device {word!r} (known: {KNOWN_TEXT})")
    for word in [w for word in words for w in _expand(word)]:
        try:
            device = make_device(word, options)
            device.start()
        except LeaderError:
            for d in started:  # a leader arm that cannot start stops the command (one line, exit 2)
                d.close()
            raise
        except (DeviceError, OSError) as exc:
            problems.append(f"{word}: {exc}")
            continue
        started.append(device)
    if require_any and not started:
        raise DeviceError("no device could start: " + "; ".join(problems))
    return started, problems
