"""The speed figures: `python -m bench.run [--json] [--quick] [--only A,B]`, which `teleop bench` runs.

bench/ lives in the source checkout beside tests/ and is not installed with the
package. Each bench module exposes `measure(quick: bool) -> dict[str, float]`;
the keys are the figures the issues name (medians or ratios, never pass/fail).
With --json, stdout carries exactly one JSON object; progress goes to stderr.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from rich.console import Console

from teleop.cli.json_output import json_stdout, print_json

MODULES = ("control", "recording", "web", "export", "devices", "generate", "eval", "e2e", "faults", "cameras", "tasks", "grasp", "review",
           "leader", "campaign", "instruct", "lerobot", "xr")
# Run only when named in --only: a train-and-evaluate loop (~30 min on 2 cores); generation on every task (~20 min); up to 48 campaign sessions;
# 300 instruction episodes (~10 min); LeRobot's own commands on the simulation (several torch processes, ~10 min)
SLOW = ("e2e", "tasks", "campaign", "instruct", "lerobot")


def run_all(quick: bool = False, only: list[str] | None = None, progress: bool = True) -> dict[str, float]:
    """Run the named bench modules (all by default) and merge their figures."""
    console = Console(stderr=True)
    results: dict[str, float] = {}
    for name in only or [m for m in MODULES if m not in SLOW]:
        if name not in MODULES:
            raise ValueError(f"unknown bench {name!r} (benches: {', '.join(MODULES)})")
        module = importlib.import_module(f"bench.{name}")
        if progress:
            console.print(f"[dim]bench {name}...[/dim]")
        results.update(module.measure(quick))
    return results


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="bench", description="measure the speed figures")
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    parser.add_argument("--quick", action="store_true", help="fewer repetitions (rougher figures)")
    parser.add_argument("--only", default=None, help=f"comma list of benches ({', '.join(MODULES)})")
    args = parser.parse_args(argv)
    only = [w.strip() for w in args.only.split(",") if w.strip()] if args.only else None
    unknown = [w for w in only or () if w not in MODULES]
    if unknown:
        print(f"bench: error: unknown bench {','.join(unknown)} (benches: {', '.join(MODULES)})", file=sys.stderr)
        return 2
    if args.json:
        with json_stdout():  # viser's banner and anything else printed go to stderr
            print_json(run_all(quick=args.quick, only=only, progress=True))
        return 0
    results = run_all(quick=args.quick, only=only, progress=True)
    for key, value in results.items():
        print(f"{key:<28} {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
