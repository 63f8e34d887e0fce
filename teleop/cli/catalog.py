"""`teleop robots` and `teleop scenes`: what robots and task scenes there are (each robot is built)."""

from __future__ import annotations

import argparse

from scenes.tasks.seed_check import DEFAULT_SEEDS
from teleop.errors import UsageError
from teleop.cli.json_output import print_json


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("robots", help="list the built-in robots")
    p.set_defaults(func=cmd_robots)
    p = sub.add_parser("scenes", help="list every task (built-in and library, or the task files given) and the robots it fits")
    p.add_argument("paths", nargs="*", metavar="PATH.toml", help="task files to check and list (default: every built-in and library task)")
    p.add_argument("--seeds", type=int, default=DEFAULT_SEEDS, metavar="N",
                   help=f"placement seeds tried per robot: a task whose objects overlap on any is refused (default {DEFAULT_SEEDS})")
    p.add_argument("--json", action="store_true", help="print exactly one JSON object")
    p.set_defaults(func=cmd_scenes)


def cmd_robots(args: argparse.Namespace) -> int:
    from scenes import BUILTIN_ROBOTS  # here, not above: `teleop --help` needs no robot built

    width = max(len(n) for n in BUILTIN_ROBOTS)
    for name, (summary, _) in BUILTIN_ROBOTS.items():
        print(f"{name:<{width}}  {summary}")
    return 0


def cmd_scenes(args: argparse.Namespace) -> int:
    """Every task with its instruction, family, objects and the robots it builds with (each robot is built)."""
    if args.seeds < 1:
        raise UsageError("--seeds must be at least 1")
    from scenes.tasks.catalog import catalog

    rows = catalog(list(args.paths) or None, seeds=args.seeds)
    if args.json:
        print_json({"task_count": len(rows), "scenes": rows})
        return 0
    width = max(len(r["name"]) for r in rows)
    for r in rows:
        px = "; ".join(f"{c} {v['object_px_at_96']:g} px" for c, v in r.get("cameras", {}).items() if c in ("front", "overhead"))
        print(f"{r['name']:<{width}}  [{r['family']}] {r['instruction']}  objects: {', '.join(r['objects'])}; "
              f"robots: {', '.join(r['robots']) or 'none'}" + (f"; smallest object at 96x96: {px}" if px else ""))
    return 0
