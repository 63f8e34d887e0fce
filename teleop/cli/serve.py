"""`teleop serve`: the browser teleop session (the main job).

Opens a page with the robot in 3D, a gizmo on each end effector, and the
buttons to record; keyboard and SpaceMouse work alongside when present.
Runs until Ctrl-C, which saves an episode in progress (marked incomplete).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

from teleop.cli.access_args import add_access_args
from teleop.cli.tls_args import add_tls_args, tls_files
from teleop.cli.session_args import add_session_args, devices_from, follower_from, session_from
from teleop.cli.signals import cancel_on_interrupt
from devices.registry import SERVE_DEVICES as DEFAULT_DEVICES

if TYPE_CHECKING:  # annotations only: the web package loads when the command runs
    from teleop.web.session_page.serve_options import ServeOptions


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "serve",
        help="teleoperate in the browser: 3D view, end-effector gizmo, record/save/discard buttons",
        description="Start a teleop session and serve it to a browser; open the printed URL. Ctrl-C stops "
        "(an episode in progress is saved, marked incomplete).",
    )
    add_session_args(p)
    p.add_argument("--device", default=",".join(DEFAULT_DEVICES),
                   help=f"comma list: gizmo, keyboard, spacemouse[:N...], so101_leader:PORT[...], instruct:SENTENCE (last) "
                        f"(default {','.join(DEFAULT_DEVICES)}; "
                        "absent ones are listed on the page; a leader arm that cannot start stops here)")
    add_access_args(p)
    add_tls_args(p)
    p.add_argument("--policy", default=None, metavar="PATH",
                   help="a LeRobot pretrained_model folder (or script:FILE) that drives; touching any device takes "
                        "over, key p or the panel's button hands back; recorded steps say who drove")
    p.add_argument("--policy-device", default="cpu", choices=("cpu", "cuda", "mps"),
                   help="torch device for the policy (default cpu)")
    p.add_argument("--keep-scene", action="store_true",
                   help="Save, Stop and Discard leave the arm and objects where they are, and the next episode starts "
                        "from there (default: they move to the next seed, the arm home)")
    p.add_argument("--status-file", type=Path, default=None, help=argparse.SUPPRESS)  # JSON status for scripts/tests
    p.set_defaults(func=cmd_serve, control_hz=None)  # None: 30 Hz, or the policy's training rate


def cmd_serve(args: argparse.Namespace) -> int:
    from teleop.web.shared.access import resolve_token

    token = resolve_token(args.host, args.token, args.no_token)  # a bad combination: one line, exit 2, at once
    options = serve_options_from(args, token)  # a bad value: one line, exit 2, before anything slow
    # Lazy: the browser server (viser, mjviser) takes 1-2 s to import; only this command needs it.
    from teleop.web.session_page.serve import serve
    from teleop.web.session_page.camera_view import warm_up
    from teleop.web.shared.net import check_port_free

    warm_up()  # find a GL backend for the camera picture while the scene compiles
    check_port_free(args.host, args.port)  # before the slow part, so a taken port fails at once
    policy = _load_policy(args) if args.policy is not None else None
    if args.control_hz is None:
        args.control_hz = getattr(policy, "trained_on", None) and policy.trained_on.fps or 30.0
    session = session_from(args, verify="background", on_error="stop")
    follower = follower_from(args, session)  # --follower: a real arm mirroring the simulated one, or None
    try:
        devices, problems = devices_from(args, session.controller.n_arms, serving=True, session=session)
        # Ctrl-C and SIGTERM stop the server, even when started with SIGINT ignored (as a background job).
        with cancel_on_interrupt(even_if_ignored=True) as stop:
            return serve(session, options, devices=devices, problems=problems, policy=policy, follower=follower,
                         stop=stop, log=lambda line: print(line, flush=True))
    finally:
        if follower is not None:
            follower.close()  # torque off however serving ended (serve() closed it already when it ran)


def serve_options_from(args: argparse.Namespace, token: str | None) -> "ServeOptions":
    """`teleop serve`'s flags as the options object; `token` as resolve_token gave it (None: open).

    The devices are opened here (a leader arm that cannot start stops the command), so whether the page's
    keys drive follows the --device words, a keyboard that could not start included.
    """
    from teleop.web.session_page.serve_options import ServeOptions, asks_for_keyboard

    tls_cert, tls_key = tls_files(args)  # --https: the self-signed pair, made on first use
    return ServeOptions(host=args.host, port=args.port, pos_speed=args.pos_speed, rot_speed=args.rot_speed, token=token,
                        no_token=args.no_token, page_keyboard=asks_for_keyboard(args.device.split(",")),
                        policy_device=args.policy_device, keep_scene=args.keep_scene, status_file=args.status_file,
                        tls_cert=tls_cert, tls_key=tls_key)


def _load_policy(args: argparse.Namespace):
    """The --policy: a script, or a checkpoint read (one line if it is not one) and then loaded by LeRobot."""
    from teleop.learn.takeover import SCRIPT_PREFIX, load_policy

    if not args.policy.startswith(SCRIPT_PREFIX):
        from teleop.cli.export import quiet_environment
        from teleop.learn.policy import Checkpoint

        quiet_environment()  # before LeRobot loads: nothing from the Hub, no wall of decoder warnings
        Checkpoint(args.policy)  # a missing or wrong folder: one line before torch loads
    return load_policy(args.policy, args.policy_device)
