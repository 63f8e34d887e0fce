"""`teleop eval`: a trained LeRobot policy in a task scene, many seeds, a success rate with its interval."""

from __future__ import annotations

import argparse
import contextlib
import math
import sys
from pathlib import Path

from scenes.numbers import number_or_nan
from teleop.errors import UsageError
from teleop.cli.json_output import print_json
from teleop.cli.variation_args import EVAL_WORDS, add_looks_seed_arg, add_range_args, variation_from


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
    p.add_argument("--policy", required=True, type=Path, metavar="PATH",
                   help="LeRobot pretrained_model folder, or script:FILE.json (a scenes/scripts JSON played as EE poses)")
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
    p.add_argument("--vary", default=None, metavar="WORDS",
                   help=f"vary each episode's scene: comma list of {EVAL_WORDS}")
    add_range_args(p, textures=True)
    add_looks_seed_arg(p, "look seed S: episodes are rendered with the held-out look seed 1000000000 + S, apart from every "
                       "training export's (default 0)")
    p.add_argument("--variation-split", default="held_out", choices=("held_out", "train"),
                   help="held_out (default): looks and physics from seeds no export or generation uses; train: from theirs")
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
    value = number_or_nan(text)
    if not (math.isfinite(value) and value > 0):
        raise UsageError(f"{flag} {text!r}: expected a positive number")
    return value


def cmd_eval(args: argparse.Namespace) -> int:
    episodes = _whole("--episodes", args.episodes, 1)
    seed = _whole("--seed", args.seed, 0)
    max_seconds = _positive("--max-seconds", args.max_seconds)
    control_hz = _positive("--control-hz", args.control_hz)
    variation = variation_from(args, "eval", split=args.variation_split)  # a bad word or range: one line, at once
    if str(args.policy).startswith("script:"):
        return _eval_script(args, episodes, seed, max_seconds, control_hz, variation)
    from teleop.cli.export import quiet_environment

    quiet_environment()  # before LeRobot loads: nothing from the Hub
    from teleop.learn.evaluate import EvalOptions, make_eval_env
    from teleop.learn.policy import Checkpoint, LeRobotPolicy

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
        variation=variation,
    )
    with contextlib.closing(make_eval_env(opts)) as env:
        checkpoint.check(env)  # mismatched features: one line before torch loads
    policy = LeRobotPolicy.load(checkpoint, device=args.device)
    return _report(args, policy, opts)


def _eval_script(args: argparse.Namespace, episodes: int, seed: int, max_seconds: float | None, control_hz: float | None,
                 variation) -> int:
    """`--policy script:FILE`: the script as EE-pose actions, looking at no camera (it reads where bodies are)."""
    from teleop.learn.evaluate import EvalOptions
    from teleop.learn.policy import ScriptedPolicy

    script = Path(str(args.policy)[len("script:"):])
    if not script.is_file():
        raise UsageError(f"--policy {args.policy}: no such script file")
    opts = EvalOptions(scene=args.scene, robot=args.robot, episodes=episodes, seed=seed, max_seconds=max_seconds,
                       control_hz=control_hz or 30.0, action=args.action or "ee_pose", cameras=(), record=args.record,
                       formats=("mcap", "hdf5") if args.format == "both" else (args.format,), progress=sys.stderr.isatty(),
                       variation=variation)
    return _report(args, ScriptedPolicy(script), opts)


def _report(args: argparse.Namespace, policy, opts) -> int:
    """Run the evaluation and print its report (one JSON object with --json)."""
    from teleop.learn.evaluate import evaluate
    from recorder import RecorderError

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
