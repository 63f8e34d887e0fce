"""`teleop serve`: the browser teleop session (the main job).

Opens a page with the robot in 3D, a gizmo on each end effector, and the
buttons to record; keyboard and SpaceMouse work alongside when present.
Runs until Ctrl-C, which saves an episode in progress (marked incomplete).
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

from teleop.errors import UsageError

DEFAULT_DEVICES = "gizmo,keyboard,spacemouse"
KNOWN_DEVICES = ("gizmo", "keyboard", "spacemouse", "script")


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    from teleop.cli_run import add_session_args

    p = sub.add_parser(
        "serve",
        help="teleoperate in the browser: 3D view, end-effector gizmo, record/save/discard buttons",
        description="Start a teleop session and serve it to a browser; open the printed URL. Ctrl-C stops "
        "(an episode in progress is saved, marked incomplete).",
    )
    add_session_args(p)
    p.add_argument("--device", default=DEFAULT_DEVICES,
                   help=f"comma list: gizmo, keyboard, spacemouse[:N...] (default {DEFAULT_DEVICES}; "
                        "absent ones are listed on the page)")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1: this machine only)")
    p.add_argument("--port", type=int, default=8080, help="port to listen on (default 8080)")
    p.add_argument("--status-file", type=Path, default=None, help=argparse.SUPPRESS)  # JSON status for scripts/tests
    p.set_defaults(func=cmd_serve)


def _start_devices(spec: str, args: argparse.Namespace, n_arms: int) -> tuple[list, list[str]]:
    """Devices that start, and one line per device that did not (absent devices are not fatal)."""
    from devices.base import DeviceError
    from devices.registry import DeviceOptions, open_devices
    from devices.script import ScriptError

    if args.pos_speed <= 0 or args.rot_speed <= 0:
        raise UsageError("--pos-speed and --rot-speed must be positive")
    words = [w.strip() for w in spec.split(",") if w.strip()]
    if not words:
        raise UsageError("--device needs at least one of gizmo, keyboard, spacemouse")
    for word in words:
        if word.split(":")[0].lower() not in KNOWN_DEVICES:
            raise UsageError(f"--device: unknown device {word!r} (known: {', '.join(KNOWN_DEVICES)})")
    options = DeviceOptions(pos_speed=args.pos_speed, rot_speed=args.rot_speed, n_arms=n_arms)
    started: list = []
    problems: list[str] = []
    for word in words:  # one at a time: a missing keyboard or SpaceMouse is listed, not fatal
        try:
            devices, caveats = open_devices(word, options)
        except ScriptError as exc:
            raise UsageError(str(exc)) from None
        except DeviceError as exc:
            problems.append(str(exc).removeprefix("no device could start: "))
            continue
        started.extend(devices)
        problems.extend(caveats)
    return started, problems


def cmd_serve(args: argparse.Namespace) -> int:
    from teleop.web.camera_view import warm_up

    warm_up()  # find a GL backend for the camera picture while the scene compiles
    from teleop.cli_run import make_session
    from teleop.web.net import check_port_free, exposure_warning

    check_port_free(args.host, args.port)  # before the slow part, so a taken port fails at once
    session = make_session(args)
    verify = session.record is not None and session.record.verify
    if session.record is not None:
        session.record.verify = False  # checked on a worker thread instead, so saving never stalls the loop
    devices, problems = _start_devices(args.device, args, session.n_arms)
    for line in problems:
        print(f"device not started: {line}", file=sys.stderr)

    from teleop.web.app import WebApp

    try:
        app = WebApp(session, devices, problems, host=args.host, port=args.port, verify=verify,
                     status_file=args.status_file, pos_speed=args.pos_speed, rot_speed=args.rot_speed)
    except BaseException:
        for d in devices:
            d.close()
        raise
    warning = exposure_warning(args.host, args.port)
    if warning:
        print(warning, file=sys.stderr)
    app.start()
    where = f", recording into {args.record}" if args.record else " (not recording: add --record DIR)"
    print(f"teleop serve: {session.robot.name} on {session.scene_name}{where}", flush=True)
    print(f"open {app.url} in a browser (Ctrl-C to stop)", flush=True)

    signal.signal(signal.SIGINT, signal.default_int_handler)  # even when started in the background with SIGINT ignored
    previous = signal.signal(signal.SIGTERM, _raise_interrupt)
    try:
        app.wait()
        if app.sim.error:
            print(f"teleop serve: control loop stopped: {app.sim.error}", file=sys.stderr)
    except KeyboardInterrupt:
        pass
    finally:
        signal.signal(signal.SIGINT, signal.SIG_IGN)  # a second Ctrl-C must not cut a file short
        signal.signal(signal.SIGTERM, previous)
        saved = app.close()
    for path in saved:
        print(f"saved {path} (incomplete: stopped mid-episode)", flush=True)
    snap = app.sim.snapshot
    print(f"teleop serve: stopped; episodes saved {snap.episodes_saved}, discarded {snap.episodes_discarded}", flush=True)
    return 1 if app.sim.error else 0


def _raise_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt
