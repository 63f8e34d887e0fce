"""Task library figures: how many tasks there are and how many `teleop generate` can grow.

Figures (`measure`):
  task_count        the built-in tasks' files plus the library's (scenes/library/*.toml)
  tasks_generating  tasks whose generation success is >= 0.8: kept / tried over SEEDS new seeds
                    (1000, ...) from 3 scripted sources (seeds 0, 1, 2, the task's first robot), 2 local workers
  tasks_table       one row per task: task, instruction, generation success, episodes/min

`TELEOP_BENCH_TASKS=a,b` limits the run to some tasks (docs/speed.md says when a subset was run).
"""

from __future__ import annotations

import os
import sys
import tempfile
from pathlib import Path

SEEDS = 50  # new seeds per task (the figure)
QUICK_SEEDS = 10
FIRST_NEW_SEED = 1000
GOOD = 0.8


def task_names() -> list[str]:
    """The built-in tasks, then the library's; `TELEOP_BENCH_TASKS=a,b` keeps some."""
    from scenes.tasks.registry import BUILTIN_ORDER, library_tasks

    names = list(BUILTIN_ORDER) + sorted(library_tasks())
    wanted = [w for w in os.environ.get("TELEOP_BENCH_TASKS", "").split(",") if w]
    return [n for n in names if not wanted or n in wanted]


def measure(quick: bool = False) -> dict:
    from bench.generate import record_sources
    from scenes.tasks.registry import find_task
    from teleop.generate.generator import GenerateOptions, generate

    seeds = QUICK_SEEDS if quick else SEEDS
    rows = []
    with tempfile.TemporaryDirectory(prefix="teleop-bench-tasks-") as tmp:
        tmp = Path(tmp)
        for name in task_names():
            try:
                sources = record_sources(name, tmp / "src" / name)
                opts = GenerateOptions(out=tmp / "gen" / name, num=seeds, seed=FIRST_NEW_SEED, workers=2,
                                       max_attempts=seeds, progress=False)
                s = generate(sources, opts, log=lambda line: None)
                rate, per_min = round(s.success_rate, 3), round(s.episodes_per_min, 1)
                note = ""
            except Exception as exc:  # a task that cannot be generated is a row with 0 and the reason, not a crashed bench
                note = str(exc).split(": ", 1)[-1].splitlines()[0]
                print(f"  {name}: {type(exc).__name__}: {exc}", file=sys.stderr)
                rate, per_min = 0.0, 0.0
            rows.append({"task": name, "instruction": find_task(name).text, "success": rate, "episodes_per_min": per_min,
                         **({"note": note} if note else {})})
            print(f"  {name}: success {rate}, {per_min} episodes/min", file=sys.stderr)
    return {"task_count": len(rows), "tasks_generating": sum(r["success"] >= GOOD for r in rows), "tasks_table": rows}


def markdown(rows: list[dict]) -> str:
    """The table of docs/speed.md, "The task library, generated"."""
    lines = ["| task | instruction | generation success | episodes/min |", "|---|---|---|---|"]
    lines += [f"| `{r['task']}` | {r['instruction']} | {r['success']:.2f}{' (' + r['note'] + ')' if r.get('note') else ''} "
              f"| {r['episodes_per_min']:.0f} |" for r in rows]
    return "\n".join(lines)
