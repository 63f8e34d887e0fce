"""Task library figures: how many tasks there are and how many `teleop generate` can grow.

Figures (`measure`):
  task_count        task files in the library (scenes/library/*.toml) plus the built-in tasks' files
  tasks_generating  tasks whose generation success is >= 0.8: kept / tried over SEEDS new seeds
                    (1000, ...) from 3 scripted sources (seeds 0, 1, 2, Panda), 2 local workers
  tasks_table       one row per task: task, instruction, generation success, episodes/min

`TELEOP_BENCH_TASKS=a,b` limits the run to some tasks (the README says when a subset was run).
"""

from __future__ import annotations

import os
import sys
import tempfile
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
LIBRARY = ROOT / "scenes" / "library"
SCRIPTS = ROOT / "scenes" / "scripts"
SEEDS = 50  # new seeds per task (the figure)
QUICK_SEEDS = 10
FIRST_NEW_SEED = 1000
GOOD = 0.8


def task_files() -> list[Path]:
    files = sorted(LIBRARY.glob("*.toml"))
    wanted = [w for w in os.environ.get("TELEOP_BENCH_TASKS", "").split(",") if w]
    return [f for f in files if not wanted or f.stem in wanted]


def record_sources(task: Path, directory: Path, seeds=(0, 1, 2)) -> list[Path]:
    """3 scripted demos of the task file through the public API, Panda, as a user would record them."""
    import teleop

    paths: list[Path] = []
    for seed in seeds:
        session = teleop.Session(scene=str(task), robot="panda", seed=seed, control_hz=30)
        script = teleop.ScriptDevice(SCRIPTS / f"{task.stem}.json")
        with teleop.Recorder(session, directory, formats=("mcap",), verify="off") as rec:
            result = teleop.run_episode(session, [script])
        if not result.success:
            raise RuntimeError(f"the scripted source of {task.stem} (seed {seed}) did not succeed")
        paths.extend(rec.paths)
    return paths


def measure(quick: bool = False) -> dict:
    from teleop.generate.generator import GenerateOptions, generate

    seeds = QUICK_SEEDS if quick else SEEDS
    rows = []
    with tempfile.TemporaryDirectory(prefix="teleop-bench-tasks-") as tmp:
        tmp = Path(tmp)
        for task in task_files():
            info = tomllib.loads(task.read_text())
            try:
                sources = record_sources(task, tmp / "src" / task.stem)
                opts = GenerateOptions(out=tmp / "gen" / task.stem, num=seeds, seed=FIRST_NEW_SEED, workers=2,
                                       max_attempts=seeds, progress=False)
                s = generate(sources, opts, log=lambda line: None)
                rate, per_min = round(s.success_rate, 3), round(s.episodes_per_min, 1)
            except Exception as exc:  # a task that cannot be generated is a row with 0, not a crashed bench
                print(f"  {task.stem}: {type(exc).__name__}: {exc}", file=sys.stderr)
                rate, per_min = 0.0, 0.0
            rows.append({"task": task.stem, "instruction": info.get("instruction", ""), "success": rate, "episodes_per_min": per_min})
            print(f"  {task.stem}: success {rate}, {per_min} episodes/min", file=sys.stderr)
    return {"task_count": len(rows), "tasks_generating": sum(r["success"] >= GOOD for r in rows), "tasks_table": rows}


def markdown(rows: list[dict]) -> str:
    """The README's table."""
    lines = ["| task | instruction | generation success | episodes/min |", "|---|---|---|---|"]
    lines += [f"| `{r['task']}` | {r['instruction']} | {r['success']:.2f} | {r['episodes_per_min']:.0f} |" for r in rows]
    return "\n".join(lines)
