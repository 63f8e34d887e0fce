"""`teleop generate`: many demonstrations from a few annotated ones (their subtasks carried to new scenes)."""

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
    g.add_argument("--source-per-arm", action="store_true",
                   help="a two-arm task: each arm chooses the source of each of its subtasks on its own (default: one "
                   "source episode for both arms; a coordinated pair always shares one)")
    g.add_argument("--format", default="mcap", choices=("mcap", "hdf5", "both"), help="file format (default mcap)")
    g.add_argument("--max-attempts", type=int, default=None, metavar="N", help="give up after N attempts (default 10 x --num + 10)")
    g.add_argument("--force-new", action="store_true",
                   help="start a new run in an --out that holds other episodes (another run's, other sources or "
                   "options) instead of refusing; without it, a re-run with the same sources and options resumes")
    g.add_argument("--force", action="store_true", help="go on even when the free space looks too small for --num episodes")
    add_physics_args(g)
    g.add_argument("--json", action="store_true", help="print one JSON object")
    g.set_defaults(func=cmd_generate)


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
        source_per_arm=args.source_per_arm,
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
