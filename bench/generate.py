"""Generation figures: success rates per task, episodes per minute, and scaling with workers.

Figures (`measure`):
  generate_success_rate_lift / _pick_place / _stack
      kept / attempts over SEEDS new seeds (1000, 1001, ...) from 3 scripted source demos
      of the task (seeds 0, 1, 2, the scripts in scenes/scripts), 2 local workers
  generate_episodes_per_min    successful lift episodes per minute of wall time, 2 workers
                               (each attempt: scene build, IK + physics, MCAP recording, a
                               bit-exact replay check; workers' start-up excluded), median of 3
  generate_scaling_2_workers   median episodes/min with 2 workers over the median with 1, the
                               same lift generation, runs alternating in this run
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
TASKS = ("lift", "pick_place", "stack")
SEEDS = 100  # new seeds per task (the figure)
QUICK_SEEDS = 20
FIRST_NEW_SEED = 1000


def record_sources(task: str, directory: Path, seeds=(0, 1, 2)) -> list[Path]:
    """3 scripted demos of `task` with its first robot and the script its task file names, as a user would record them."""
    import teleop
    from scenes.tasks.registry import find_task

    spec = find_task(task)
    robot = spec.robots[0]
    paths: list[Path] = []
    for seed in seeds:
        session = teleop.Session(scene=task, robot=robot, seed=seed, control_hz=30)
        script = teleop.ScriptDevice(spec.script_for(robot))
        with teleop.Recorder(session, directory, formats=("mcap",), verify="off") as rec:
            result = teleop.run_episode(session, [script])
        if not result.success:
            raise RuntimeError(f"the scripted {task} source (seed {seed}) did not succeed")
        paths.extend(rec.paths)
    return paths


def _generate(sources: list[Path], out: Path, num: int, workers: int, attempts: int):
    from teleop.generate.generator import GenerateOptions, generate

    opts = GenerateOptions(out=out, num=num, seed=FIRST_NEW_SEED, workers=workers, max_attempts=attempts,
                           progress=False)
    return generate(sources, opts, log=lambda line: None)


def measure(quick: bool = False) -> dict[str, float]:
    seeds = QUICK_SEEDS if quick else SEEDS
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="teleop-bench-generate-") as tmp:
        tmp = Path(tmp)
        sources = {task: record_sources(task, tmp / "src" / task) for task in TASKS}
        for task, paths in sources.items():
            # num = seeds with max_attempts = seeds: every seed is tried once, the rate is kept / tried
            s = _generate(paths, tmp / "gen" / task, seeds, workers=2, attempts=seeds)
            out[f"generate_success_rate_{task}"] = round(s.success_rate, 3)
            print(f"  {task}: {s.successes}/{s.attempts} kept in {s.seconds:.1f} s", file=sys.stderr)
        n = 10 if quick else 30
        rates: dict[int, list[float]] = {1: [], 2: []}
        for i, workers in enumerate((1, 2) if quick else (1, 2, 1, 2, 1, 2)):  # alternating: the machine drifts
            s = _generate(sources["lift"], tmp / f"speed{i}", n, workers=workers, attempts=3 * n)
            rates[workers].append(s.episodes_per_min)
            print(f"  lift, {workers} worker(s): {s.episodes_per_min:.1f} episodes/min", file=sys.stderr)
        one, two = statistics.median(rates[1]), statistics.median(rates[2])
        out["generate_episodes_per_min"] = round(two, 1)
        out["generate_scaling_2_workers"] = round(two / one, 2) if one else 0.0
    return out
