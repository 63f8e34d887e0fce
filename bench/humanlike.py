"""A solving script made to move the way a person at a keyboard moves it: human-like sources.

    python bench/humanlike.py SCRIPT.json --seed S > human_S.json

A scripted source goes straight to each target at one speed. A person holding keys
does not: they pause to look, go slower, overshoot a target by a centimetre or
three and come back, and hesitate before closing the gripper. This rewrites a
script (docs/recording.md, "Scripts") step by step, seeded:

- a pause of 0.2-0.8 s before a step, half the time;
- every step 1.0-1.6x as long;
- a `to_body` / `to` target first reached 1-3 cm off sideways (and up to 2 cm too high, never
  lower: no pushing into the table), then corrected in 0.4-0.8 s;
- a `move` carried 10-30 % too far, then brought back;
- a 0.3-0.7 s hesitation before the gripper closes.

The result still solves the task (the corrections end where the original steps end),
which `bench/train_eval.sh --humanlike` checks by recording it.

A two-arm script (steps with `arm`) is rewritten for each arm with a draw of its own
(seeded by the seed and the arm), so the two hands pause, miss and correct at different
times; a step without an arm (a pause) belongs to arm 0. A one-arm script is rewritten as before.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def _off_target(rng: np.random.Generator) -> np.ndarray:
    """A sideways miss of 1-3 cm in a random direction, and 0-2 cm too high."""
    angle = rng.uniform(0, 2 * np.pi)
    dist = rng.uniform(0.01, 0.03)
    return np.array([dist * np.cos(angle), dist * np.sin(angle), rng.uniform(0.0, 0.02)])


def humanlike(steps: list[dict], seed: int) -> list[dict]:
    """The script's steps with a person's pauses, overshoots and corrections (seeded; per arm for two arms)."""
    arms = sorted({int(step.get("arm", 0)) for step in steps})
    rngs = {arm: np.random.default_rng(seed if len(arms) == 1 else [seed, arm]) for arm in arms}
    out: list[dict] = []
    for step in steps:
        rng = rngs[int(step.get("arm", 0))]
        arm = {"arm": step["arm"]} if "arm" in step else {}  # a pause or a correction stays with its arm
        if rng.random() < 0.5:
            out.append({"duration": round(float(rng.uniform(0.2, 0.8)), 3), **arm})
        step = dict(step)
        duration = float(step.get("duration", 0.0)) * float(rng.uniform(1.0, 1.6))
        correction = round(float(rng.uniform(0.4, 0.8)), 3)
        if step.get("gripper") == "close" and not any(k in step for k in ("move", "to", "to_body", "rotate")):
            out.append({"duration": round(float(rng.uniform(0.3, 0.7)), 3), **arm})
        if "to_body" in step or "to" in step:
            miss = _off_target(rng)
            first = dict(step, duration=round(duration, 3))
            if "to_body" in step:
                first["offset"] = [round(float(v), 4) for v in np.asarray(step.get("offset", [0, 0, 0])) + miss]
            else:
                first["to"] = [round(float(v), 4) for v in np.asarray(step["to"]) + miss]
            fix = {k: v for k, v in step.items() if k not in ("gripper", "duration")}
            out += [first, dict(fix, duration=correction)]
        elif "move" in step:
            move = np.asarray(step["move"], dtype=float)
            extra = move * float(rng.uniform(0.1, 0.3))
            out += [dict(step, move=[round(float(v), 4) for v in move + extra], duration=round(duration, 3)),
                    {"duration": correction, "move": [round(float(v), 4) for v in -extra], **arm}]
        else:
            out.append(dict(step, duration=round(duration, 3)))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("script", type=Path)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    try:
        steps = json.loads(args.script.read_text())["steps"]
    except (OSError, ValueError, KeyError) as exc:
        print(f"humanlike.py: {args.script}: {exc}", file=sys.stderr)
        return 2
    json.dump({"steps": humanlike(steps, args.seed)}, sys.stdout, indent=1)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
