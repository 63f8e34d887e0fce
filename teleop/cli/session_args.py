"""The session flags `teleop run` and `teleop serve` share, and the Session and devices they ask for.

What the flags open is teleop/control/session_setup.py's; here the flags are read.
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from teleop.cli.variation_args import add_physics_args, variation_from

if TYPE_CHECKING:  # annotations only: MuJoCo and mink load when a session opens, LeRobot only with --follower
    from devices.base import Device
    from teleop.control.follower import Follower
    from teleop.control.session import Session


def add_session_args(p: argparse.ArgumentParser) -> None:
    """Flags shared by `run` and `serve`."""
    p.add_argument("--scene", default="lift", help="task scene (default lift; see `teleop scenes`)")
    p.add_argument("--robot", default="panda", help="built-in robot name or PATH.toml (default panda)")
    p.add_argument("--seed", type=int, default=0, help="object placement seed (default 0)")
    p.add_argument("--control-hz", type=float, default=30.0, help="control rate in Hz (default 30)")
    p.add_argument("--record", type=Path, default=None, metavar="DIR", help="record episodes into DIR")
    p.add_argument("--format", default="mcap", choices=("mcap", "hdf5", "both"), help="recording format (default mcap)")
    p.add_argument("--no-verify", action="store_true", help="skip the exact-replay check after each saved episode")
    p.add_argument("--pos-speed", type=float, default=0.15, help="hold-to-move speed, m/s (default 0.15)")
    p.add_argument("--rot-speed", type=float, default=0.8, help="hold-to-rotate speed, rad/s (default 0.8)")
    add_physics_args(p)
    p.add_argument("--follower", default=None, metavar="SPEC",
                   help="a real arm that mirrors the simulated one: so101_follower:PORT[:id=NAME][:calibration=DIR]"
                        "[:map=FILE][:max_step=DEG] (with --robot so101; each joint moves at most max_step degrees a tick, default 5; "
                        "the session then runs in real time)")
    p.add_argument("--instruct-state", action="store_true",
                   help="instruct:SENTENCE reads object positions from the simulator's state, not the camera (to compare)")
    p.add_argument("--instruct-camera", default="front", metavar="NAME", help="the camera instruct:SENTENCE looks through (default front)")
    p.add_argument("--plan-url", default=None, metavar="URL",
                   help="an OpenAI-compatible chat-completions endpoint that plans instruct:SENTENCE (default: the rule planner)")


def session_from(args: argparse.Namespace, verify: str = "sync", on_error: str = "raise") -> Session:
    """The Session of the shared flags, recording into --record when given."""
    from teleop.control.session_setup import check_record_dir, open_session

    check_record_dir(args.record)
    variation = variation_from(args, "generation")  # a bad --vary word or range: one line, before the scene builds
    return open_session(
        args.scene, args.robot, args.seed, args.control_hz, variation=variation, record=args.record,
        formats=("mcap", "hdf5") if args.format == "both" else (args.format,),
        verify="off" if args.no_verify else verify, on_error=on_error,
    )


def follower_from(args: argparse.Namespace, session: Session) -> "Follower | None":
    """The real follower of --follower, connected and mirroring `session` (None without the flag).

    A bad value, a robot it cannot mirror or an arm that cannot be reached: one line, before anything is recorded.
    """
    if getattr(args, "follower", None) is None:
        return None
    from teleop.control.follower import open_follower
    from teleop.control.follower_spec import check_pairing, parse_follower_spec

    check_pairing(parse_follower_spec(args.follower), session.robot.name)  # before LeRobot loads (seconds)
    return open_follower(args.follower, session, devices=getattr(args, "device", None))  # a leader's map= is the follower's too


def devices_from(args: argparse.Namespace, n_arms: int, serving: bool = False,
                 log: Callable[[str], None] | None = None, session: Session | None = None) -> tuple[list[Device], list[str]]:
    """The devices of --device at --pos-speed / --rot-speed (see open_session_devices); an instruct:SENTENCE plans
    with --instruct-state / --instruct-camera / --plan-url and notes each plan in `session`'s episodes."""
    from teleop.control.session_setup import open_session_devices

    return open_session_devices(args.device, n_arms, args.pos_speed, args.rot_speed, serving=serving, log=log,
                                planner=instruct_planner(args, session))


def instruct_planner(args: argparse.Namespace, session: Session | None):
    """instruct:SENTENCE -> its planner, from the instruct flags (teleop.instruct; loaded only when used)."""
    if "instruct:" not in args.device.lower():
        return None
    from teleop.instruct.session_plan import InstructOptions, make_planner

    options = InstructOptions(state=args.instruct_state, camera=args.instruct_camera, plan_url=args.plan_url)

    def note(plan: dict) -> None:  # the episode says where it came from: the sentence, the positions, the steps
        if session is not None and session.recorder is not None:
            session.recorder.provenance["generator"] = plan

    return lambda sentence: make_planner(sentence, options, on_note=note)
