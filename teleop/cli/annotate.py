"""`teleop annotate`: show or find the subtasks of recorded episodes (a sidecar beside each file)."""

from __future__ import annotations

import argparse
from pathlib import Path

from teleop.errors import UsageError
from teleop.cli.json_output import print_json


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


def cmd_annotate(args: argparse.Namespace) -> int:
    from recorder.disk import WriteError
    from replay.subtasks.annotate import annotate
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
        parts = ", ".join(f"{s['arm'] + ' ' if s.get('arm') else ''}{s['object']} {s['start']}-{s['end']}" for s in ep["subtasks"])
        print(f"{ep['path']}: {parts}" + (" (found automatically, saved)" if ep["by"] == "auto" else ""))
    return 0
