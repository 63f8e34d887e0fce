"""`teleop annotate` and `teleop generate`: subtasks of a few demonstrations, then many more like them."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from teleop.errors import UsageError
from teleop.cli.json_output import print_json
from teleop.cli.signals import cancel_on_interrupt
from teleop.cli.variation_args import add_physics_args, variation_from


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser(
        "annotate",
        help="show or find the subtasks of recorded episodes (stored beside each file)",
        description="Show each episode's subtask boundaries; --auto finds them from the recorded gripper "
        "commands and contacts and stores them beside the episode (EPISODE.subtasks.json). "
        "Edit them in the replay viewer: teleop replay EPISODE --serve.",
    )
    p.add_argument("paths", nargs="+", type=Path, metavar="EPISODE", help="episode files or directories of them")
    p.add_argument("--auto", action="store_true", help="find the boundaries automatically (replaces stored ones)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=cmd_annotate)

    g = sub.add_parser(
        "generate",
        help="generate demonstrations from a few recorded ones (MimicGen's method), in parallel",
        description="For each new seed, carry each subtask of a source episode into the new scene relative "
        "to its object, execute it, and keep the runs that succeed. Sources are annotated automatically "
        "when they are not yet.",
    )
    g.add_argument("sources", nargs="+", type=Path, metavar="SOURCE", help="source episode files or directories")
    g.add_argument("--out", type=Path, required=True, metavar="DIR", help="directory for the generated episodes")
    g.add_argument("--num", type=int, required=True, metavar="N", help="successful episodes to keep")
    g.add_argument("--seed", type=int, default=0, metavar="S", help="first scene seed (then S+1, S+2, ...; default 0)")
    g.add_argument("--workers", type=int, default=None, metavar="K", help="local worker processes (default: the cores)")
    g.add_argument("--ray", default=None, metavar="ADDRESS", help="run on a Ray cluster: 'auto' or HOST:PORT (needs .[cluster])")
    g.add_argument("--keep-failures", action="store_true", help="also keep failed attempts (in DIR/failures, success false)")
    g.add_argument("--format", default="mcap", choices=("mcap", "hdf5", "both"), help="file format (default mcap)")
    g.add_argument("--max-attempts", type=int, default=None, metavar="N", help="give up after N attempts (default 10 x --num + 10)")
    g.add_argument("--force-new", action="store_true",
                   help="start a new run in an --out that holds other episodes (another run's, other sources or "
                   "options) instead of refusing; without it, a re-run with the same sources and options resumes")
    g.add_argument("--force", action="store_true", help="go on even when the free space looks too small for --num episodes")
    add_physics_args(g)
    g.add_argument("--json", action="store_true", help="print one JSON object")
    g.set_defaults(func=cmd_generate)


def cmd_annotate(args: argparse.Namespace) -> int:
    from recorder.disk import WriteError
    from replay.annotate import annotate
    from replay.episode import find_episodes

    files = find_episodes(args.paths)
    if not files:
        raise UsageError("no episode files found in " + ", ".join(str(p) for p in args.paths))
    episodes = []
    for path in files:
        try:
            subtasks, how = annotate(path, auto=args.auto)
        except WriteError as exc:  # a full disk: the sidecars saved before stay, none is half-written
            if args.json:
                print_json({"episodes": episodes, "error": str(exc)})
            raise WriteError(f"{exc} ({len(episodes)} of {len(files)} episodes annotated)"
                             if episodes else str(exc)) from None
        episodes.append({"path": str(path), "by": how, "subtasks": [s.to_json() for s in subtasks]})
    if args.json:
        print_json({"episodes": episodes})
        return 0
    for ep in episodes:
        parts = ", ".join(f"{s['object']} {s['start']}-{s['end']}" for s in ep["subtasks"])
        print(f"{ep['path']}: {parts}" + (" (found automatically, saved)" if ep["by"] == "auto" else ""))
    return 0


def cmd_generate(args: argparse.Namespace) -> int:
    from recorder.disk import NotEnoughSpace, WriteError
    from teleop.generate.generator import GenerateOptions, generate

    if args.max_attempts is not None and args.max_attempts <= 0:
        raise UsageError(f"--max-attempts must be positive, got {args.max_attempts}")
    opts = GenerateOptions(
        out=args.out,
        num=args.num,
        seed=args.seed,
        workers=args.workers,
        ray=args.ray,
        keep_failures=args.keep_failures,
        formats=("mcap", "hdf5") if args.format == "both" else (args.format,),
        max_attempts=args.max_attempts,
        progress=sys.stderr.isatty(),
        force_new=args.force_new,
        force=args.force,
        variation=variation_from(args, "generation"),
    )
    try:
        with cancel_on_interrupt() as cancel:  # Ctrl-C: the workers stop, what was kept stays
            summary = generate(args.sources, opts, cancel=cancel)
    except WriteError as exc:  # a full disk: one line (main prints it), exit 2; the episodes kept stay whole
        done = getattr(exc, "summary", None)
        if args.json and done is not None:
            done.error = str(exc)
            print_json(done.to_json())
        kept = done.resumed_from + done.successes if done is not None else 0
        raise WriteError(f"{exc} ({kept} episodes kept in {args.out}; run the same command again to resume)"
                         if kept and not isinstance(exc, NotEnoughSpace) else str(exc)) from None
    if args.json:
        print_json(summary.to_json())
    else:
        print(summary.line())
    if summary.interrupted:
        return 130
    return 0 if summary.resumed_from + summary.successes >= args.num else 1
