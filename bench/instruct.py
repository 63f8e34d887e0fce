"""From a sentence to a demonstration: what perception costs (issue 59).

Figures (`measure`):
  perceive_error_mm      median and p95 position error (mm) of every object fully in view, over SEEDS seeds of
                         lift, stack and pick_place (panda, `front` at 224x224), estimate against the body's position
  perceive_ms            median time (ms) to estimate every object from one 224x224 RGB-D view (on the CPU)
  perceive_with_render_ms  the same with the view rendered (the offscreen GL backend: EGL or OSMesa)
  instruct_success       per task (lift, stack, pick_place): the success rate of the task's own instruction over
                         SEEDS seeds with positions from the camera and from the state, each with its 95 % Wilson
                         interval: the gap is what perception costs
"""

from __future__ import annotations

import math
import sys
import time

import numpy as np

TASKS = ("lift", "stack", "pick_place")
SEEDS = 50
QUICK_SEEDS = 3


def wilson(successes: int, n: int, z: float = 1.959963984540054) -> list[float]:
    """95 % Wilson score interval of a success rate."""
    if n == 0:
        return [0.0, 1.0]
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return [round(max(0.0, centre - half), 3), round(min(1.0, centre + half), 3)]


def perception_errors(seeds: int) -> tuple[list[float], list[tuple[float, float]]]:
    """(errors in mm of the objects fully in view, (ms to render and estimate, ms to estimate) per view) over `seeds`
    seeds of each task."""
    from teleop.control.session import Session
    from teleop.instruct.compare import compared
    from teleop.instruct.perceive import RgbdCamera

    errors, times = [], []
    rgbd = None
    for task in TASKS:
        session = Session(scene=task, robot="panda", seed=0, control_hz=30)
        for seed in range(seeds):
            session.reset(seed)
            c = session.controller
            if rgbd is None:
                rgbd = RgbdCamera(c.model, 224, 224)
            rgbd.load(c.model)
            t0 = time.perf_counter()
            seen, rows = compared(c, rgbd=rgbd)
            times.append(((time.perf_counter() - t0) * 1000, seen.ms))
            errors += [r["error_m"] * 1000 for r in rows if r["visible"]]
        session.close()
    if rgbd is not None:
        rgbd.close()
    return errors, times


def success_rate(task: str, seeds: int, state: bool) -> tuple[int, int]:
    """(successes, episodes) of the task's own instruction over `seeds` seeds."""
    from devices.planned import PlannedDevice
    from scenes.tasks.registry import find_task
    from teleop.control.loop import run_episode
    from teleop.control.session import Session
    from teleop.instruct.session_plan import InstructOptions, make_planner

    sentence = find_task(task).text
    device = PlannedDevice(sentence, make_planner(sentence, InstructOptions(state=state)))
    session = Session(scene=task, robot="panda", seed=0, control_hz=30)
    wins = 0
    for seed in range(seeds):
        session.reset(seed)
        device.restart()
        wins += bool(run_episode(session, [device]).success)
    session.close()
    return wins, seeds


def measure(quick: bool = False) -> dict:
    seeds = QUICK_SEEDS if quick else SEEDS
    errors, times = perception_errors(seeds)
    results: dict = {
        "perceive_error_mm": {"median": round(float(np.median(errors)), 2), "p95": round(float(np.percentile(errors, 95)), 2),
                              "objects": len(errors)},
        "perceive_ms": round(float(np.median([t[1] for t in times])), 2),
        "perceive_with_render_ms": round(float(np.median([t[0] for t in times])), 2),
    }
    success: dict = {}
    for task in TASKS:
        row: dict = {"seeds": seeds}
        for source in ("camera", "state"):
            wins, n = success_rate(task, seeds, state=source == "state")
            row[source] = round(wins / n, 3)
            row[f"{source}_ci95"] = wilson(wins, n)
        success[task] = row
        print(f"instruct: {task}: camera {row['camera']:.2f} {row['camera_ci95']}, state {row['state']:.2f} {row['state_ci95']}",
              file=sys.stderr)
    results["instruct_success"] = success
    return results
