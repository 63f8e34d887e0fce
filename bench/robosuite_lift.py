"""robosuite's own Lift Panda step, timed in its own interpreter for bench/control.py.

robosuite 1.5.2 runs on mujoco 3.3.x, not on the mujoco 4 of our venv, so the
bench starts this script with a separate Python (TELEOP_ROBOSUITE_PYTHON, or
.venv-robosuite/bin/python made by
`python3.12 -m venv .venv-robosuite && .venv-robosuite/bin/pip install robosuite==1.5.2 'mujoco==3.3.*'`).
It imports nothing of ours. Protocol on stdin/stdout, one line each: it prints
"ready" once the environment is built and warmed up; then for each line "K" it
runs K env.step calls and prints their wall times (ms) as a JSON list; EOF ends it.

The environment matches the bench's own tick: Lift with one Panda, robosuite's
default controller (OSC pose), 20 Hz control on 2 ms physics steps (25 per
step), no rendering or camera observations; the action circles the hand.
"""

from __future__ import annotations

import json
import math
import sys
import time

WARMUP_STEPS = 100


def main() -> int:
    import numpy as np
    import robosuite

    env = robosuite.make(
        "Lift", robots="Panda", has_renderer=False, has_offscreen_renderer=False, use_camera_obs=False,
        control_freq=20, ignore_done=True,
    )
    env.reset()
    action = np.zeros(env.action_dim)
    tick = 0

    def step() -> float:
        nonlocal tick
        a = tick * 0.05
        action[0], action[1], action[2] = 0.3 * math.cos(a), 0.3 * math.sin(a), 0.1 * math.sin(2 * a)
        tick += 1
        t0 = time.perf_counter()
        env.step(action)
        return (time.perf_counter() - t0) * 1e3

    for _ in range(WARMUP_STEPS):
        step()
    print("ready", flush=True)
    for line in sys.stdin:
        k = int(line)
        print(json.dumps([step() for _ in range(k)]), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
