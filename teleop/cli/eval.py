"""`teleop eval`: a trained LeRobot policy in a task scene, many seeds, a success rate with its interval."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

from teleop.errors import UsageError
from teleop.cli.json_output import print_json


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "eval",
        help="evaluate a trained LeRobot policy in a scene: success rate over many seeds",
        description="Run a LeRobot pretrained-model folder (lerobot-train's checkpoints/<step>/pretrained_model) "
        "in a task scene for N episodes on new seeds, observed and driven as the export records them, and "
        "report the success rate with a 95% Wilson interval, the mean time to success and each seed's outcome. "
        "Cameras and image size come from the policy; the action mode and control rate from its training "
        "dataset where train_config.json names one that is here.",
    )
    p.add_argument("--policy", required=True, type=Path, metavar="PATH", help="LeRobot pretrained_model folder")
    p.add_argument("--scene", default="lift", help="task scene (default lift)")
    p.add_argument("--robot", default="panda", help="built-in robot name or PATH.toml (default panda)")
    p.add_argument("--episodes", default="50", metavar="N", help="episodes, one scene seed each (default 50)")
    p.add_argument("--seed", default="1000", metavar="S",
                   help="first scene seed, then S+1, ... (default 1000: past the seeds recordings start from)")
    p.add_argument("--max-seconds", default="20", metavar="T", help="simulated seconds before an episode counts as failed (default 20)")
    p.add_argument("--record", type=Path, default=None, metavar="DIR",
                   help="record every rollout as an episode file (source policy; watch with teleop replay DIR --serve)")
    p.add_argument("--format", default="mcap", choices=("mcap", "hdf5", "both"), help="recording format (default mcap)")
    p.add_argument("--device", default="cpu", choices=("cpu", "cuda", "mps"), help="torch device for the policy (default cpu)")
    p.add_argument("--action", default=None, choices=("joint", "ee_delta", "ee_pose"),
                   help="action mode (default: the training dataset's, else joint)")
    p.add_argument("--control-hz", default=None, metavar="HZ", help="control rate (default: the training dataset's fps, else 30)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_eval)


def _whole(flag: str, text: str, least: int) -> int:
    """A whole-number flag, checked here so a bad value is the one error line (argparse adds its usage)."""
    try:
        value = int(text)
    except ValueError:
        value = least - 1
    if value < least:
        raise UsageError(f"{flag} {text!r}: expected a whole number, {least} or more")
    return value


def _positive(flag: str, text: str | None) -> float | None:
    if text is None:
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{flag} {text!r}: expected a positive number")
    return value


def cmd_eval(args: argparse.Namespace) -> int:
    episodes = _whole("--episodes", args.episodes, 1)
    seed = _whole("--seed", args.seed, 0)
    max_seconds = _positive("--max-seconds", args.max_seconds)
    control_hz = _positive("--control-hz", args.control_hz)
    from teleop.cli.export import quiet_environment

    quiet_environment()  # before LeRobot loads: nothing from the Hub
    from teleop.learn.evaluate import EvalOptions, evaluate, make_eval_env
    from teleop.learn.policy import Checkpoint, LeRobotPolicy
    from recorder import RecorderError

    checkpoint = Checkpoint(args.policy)  # a missing or wrong folder: one line before torch loads
    implied = checkpoint.env_options()
    opts = EvalOptions(
        scene=args.scene,
        robot=args.robot,
        episodes=episodes,
        seed=seed,
        max_seconds=max_seconds,
        control_hz=control_hz or implied.get("control_hz", 30.0),
        action=args.action or implied.get("action", "joint"),
        cameras=list(checkpoint.trained_on.cameras),
        image_size=implied.get("image_size"),
        record=args.record,
        formats=("mcap", "hdf5") if args.format == "both" else (args.format,),
        progress=sys.stderr.isatty(),
    )
    with contextlib.closing(make_eval_env(opts)) as env:
        checkpoint.check(env)  # mismatched features: one line before torch loads
    policy = LeRobotPolicy.load(checkpoint, device=args.device)
    try:
        summary = evaluate(policy, opts)
    except RecorderError as exc:  # a full disk under --record: one line (main prints it), exit 2
        done = getattr(exc, "summary", None)
        if args.json and done is not None:
            print_json(done.to_json())  # the rollouts done, and the error
        raise
    if args.json:
        print_json(summary.to_json())
    else:
        print("\n".join(summary.lines()))
    return 130 if summary.interrupted else 0
