"""Lift success against the data it was trained on: the learning curve of issue 21.

    python bench/learning_curve.py [--steps N] [--jobs J] [--work DIR]

Runs bench/train_eval.sh on lift from human-like sources (bench/humanlike.py: a
person's pauses, overshoots and corrections) for
- 10, 50 and 200 generated demos from 3 sources, and
- 200 generated demos from 1 source,
exported as the recipe exports, idle frames left out (a person's pauses: with them in, no run lifted the cube),
each evaluated on seeds 1000-1049, then writes docs/learning_curve.png (success rate
with its 95 % Wilson interval) and docs/learning_curve.json (the runs' JSON), and prints
the JSON object of all runs on stdout. Runs already in WORK with the same settings are reused.
--jobs 2 trains two runs side by side, each with one data worker (on 2 cores: 5-8 steps/s each,
against 10-14 for one run alone with two workers). 10,000 steps by default, against the recipe's
18,000: the four runs then take about an hour with --jobs 2 instead of two.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
RUNS = [(10, 3), (50, 3), (200, 3), (200, 1)]  # (generated demos, human-like sources)


def run(demos: int, sources: int, steps: int, work: Path, workers: int | None = None) -> dict:
    out = work / f"lift-d{demos}-s{sources}h-idle"
    env = {**os.environ, **({"WORKERS": str(workers)} if workers else {})}
    proc = subprocess.run(
        ["bash", str(ROOT / "bench" / "train_eval.sh"), "lift", "--demos", str(demos), "--sources", str(sources),
         "--humanlike", "--steps", str(steps), "--work", str(out)],
        stdout=subprocess.PIPE, stderr=sys.stderr, text=True, check=True, env=env,
    )
    return json.loads(proc.stdout.strip().splitlines()[-1])


def plot(results: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(9, 3.6), gridspec_kw={"width_ratios": [2, 1]})
    three = sorted((r for r in results if r["sources"] == 3), key=lambda r: r["demos"])
    xs = [r["demos"] for r in three]
    ys = [r["success_rate"] for r in three]
    err = [[y - r["ci95"][0] for y, r in zip(ys, three)], [r["ci95"][1] - y for y, r in zip(ys, three)]]
    left.errorbar(xs, ys, yerr=err, marker="o", capsize=4)
    left.set_xscale("log")
    left.set_xticks(xs, [str(x) for x in xs])
    left.set_xlabel("generated demos (from 3 human-like sources)")
    left.set_ylabel("lift success, 50 new seeds")
    left.set_ylim(0, 1.02)
    left.grid(alpha=0.3)
    at200 = sorted((r for r in results if r["demos"] == 200), key=lambda r: r["sources"])
    names = [f"{r['sources']} source{'s' * (r['sources'] != 1)}" for r in at200]
    rates = [r["success_rate"] for r in at200]
    yerr = [[y - r["ci95"][0] for y, r in zip(rates, at200)], [r["ci95"][1] - y for y, r in zip(rates, at200)]]
    right.bar(names, rates, yerr=yerr, capsize=4, color=["#7aa6d6", "#2f6db3"][: len(names)])
    right.set_ylim(0, 1.02)
    right.set_title("200 generated demos", fontsize=10)
    right.grid(alpha=0.3, axis="y")
    steps = results[0]["steps"] if results else 0
    fig.suptitle(f"ACT on robot + object state, {steps} training steps on 2 CPU cores (95 % Wilson intervals)", fontsize=10)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=10000)
    parser.add_argument("--jobs", type=int, default=1, help="runs trained side by side")
    parser.add_argument("--work", type=Path, default=ROOT / "out" / "learning_curve")
    args = parser.parse_args(argv)
    workers = 1 if args.jobs > 1 else None
    with ThreadPoolExecutor(max(1, args.jobs)) as pool:
        results = list(pool.map(lambda r: run(r[0], r[1], args.steps, args.work, workers), RUNS))
    (ROOT / "docs").mkdir(exist_ok=True)
    (ROOT / "docs" / "learning_curve.json").write_text(json.dumps(results, indent=1) + "\n")
    plot(results, ROOT / "docs" / "learning_curve.png")
    print(json.dumps({"runs": results}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
