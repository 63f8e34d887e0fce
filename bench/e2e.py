"""The loop, measured end to end (issue 21): `teleop bench --only e2e` runs bench/train_eval.sh on lift.

3 scripted sources -> 200 generated demos -> export (robot state + objects' poses, no
images) -> lerobot-train ACT on this machine's CPU -> `teleop eval` on seeds 1000-1049.
Figures: e2e_lift_success_rate with its 95 % Wilson interval (e2e_lift_ci95), the
training time in seconds, and the demos it trained on. The work directory
(out/e2e/bench-lift) is made afresh each run. Not in a plain `teleop bench`:
it takes ~27 minutes on 2 cores (6,000 steps: the whole run within 30, docs/learning.md).
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def measure(quick: bool) -> dict:
    work = ROOT / "out" / "e2e" / "bench-lift"
    shutil.rmtree(work, ignore_errors=True)
    args = ["--demos", "50", "--steps", "300"] if quick else []
    proc = subprocess.run(["bash", str(ROOT / "bench" / "train_eval.sh"), "lift", "--work", str(work), *args],
                          stdout=subprocess.PIPE, stderr=sys.stderr, text=True, check=True)
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    return {
        "e2e_lift_success_rate": report["success_rate"],
        "e2e_lift_ci95": report["ci95"],
        "e2e_lift_train_seconds": report["train_seconds"],
        "e2e_lift_demos": report["demos"],
        "e2e_lift_failure_breakdown": report["failure_breakdown"],
    }
