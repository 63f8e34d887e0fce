"""`teleop bench`: the speed figures the issues name, measured by the checkout's bench/ in a fresh process."""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

from teleop.cli.json_output import print_json
from teleop.errors import UsageError


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Register this module's subcommands."""
    p = sub.add_parser("bench", help="measure the speed figures the issues name")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--quick", action="store_true", help="fewer repetitions (rougher figures)")
    p.add_argument("--only", default=None,
                   help="comma list of benches to run (control, recording, web, export, devices, generate, eval, faults, cameras, grasp, "
                        "review, leader;"
                        " run only when named: e2e, tasks, campaign)")
    p.set_defaults(func=cmd_bench)


def cmd_bench(args: argparse.Namespace) -> int:
    """Run the checkout's bench/ (not installed with the package) in a fresh process and pass its figures on."""
    root = Path(__file__).resolve().parents[2]
    if not (root / "bench" / "run.py").is_file():
        raise UsageError("the bench needs a source checkout: bench/ is not installed with the package")
    benches = sorted(p.stem for p in (root / "bench").glob("*.py") if "\ndef measure(" in p.read_text())  # bench modules
    unknown = [w.strip() for w in (args.only or "").split(",") if w.strip() and w.strip() not in benches]
    if unknown:
        raise UsageError(f"--only {','.join(unknown)}: unknown bench (benches: {', '.join(benches)})")
    flags = [*(["--quick"] if args.quick else []), *(["--only", args.only] if args.only else []), "--json"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(root), *filter(None, [os.environ.get("PYTHONPATH")])])}
    done = subprocess.run([sys.executable, "-m", "bench.run", *flags], cwd=root, env=env, stdout=subprocess.PIPE,
                          stderr=None, text=True)
    if done.returncode != 0:
        raise UsageError(f"the bench failed (exit {done.returncode}); its output is above")
    try:
        results = json.loads(done.stdout)
    except ValueError:
        raise UsageError("the bench printed something other than its figures on stdout") from None
    if args.json:
        print_json(results)
    else:
        for key, value in results.items():
            print(f"{key:<28} {value}")
    return 0
