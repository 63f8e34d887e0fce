"""Evaluation figures: environment steps per second with a small policy, and one env step alone.

Figures (`measure`), lift with the Panda, joint actions, 30 Hz, cameras front and
wrist rendered at 96x96 by the export's renderer:
  eval_steps_per_s       environment steps per second of wall time in `teleop.learn.evaluate`'s
                         loop (observe, policy on the CPU, step), median over episodes
                         of 2 simulated seconds (60 steps; scene build and reset included)
  eval_policy_ms         median time of the small policy's select_action alone
  env_step_ms            median time of env.step without a policy (a fixed hold action):
                         IK-free joint control, physics, the observation and its 2 images
  env_step_no_images_ms  the same with no cameras (vectors only)

The small policy is a torch CNN (two conv layers per camera, an MLP; ~40k parameters)
behind the same `Policy` interface as a LeRobot checkpoint, on 1 CPU thread.
"""

from __future__ import annotations

import statistics
import time

import numpy as np

SIZE = (96, 96)
CAMERAS = ("front", "wrist")
HZ = 30.0


def _small_policy():
    """A tiny CNN policy (torch, optional heavy dependency: imported here only)."""
    import torch
    from torch import nn

    class SmallPolicy:
        name = "bench:small-cnn"

        def attach(self, env) -> None:
            env = env.unwrapped
            self.images = [k for k in env.features if k.startswith("observation.images.")]
            n_state = env.features["observation.state"]["shape"][0]
            n_action = env.features["action"]["shape"][0]
            torch.manual_seed(0)
            self.encoder = nn.Sequential(
                nn.Conv2d(3, 16, 5, stride=4), nn.ReLU(), nn.Conv2d(16, 32, 3, stride=2), nn.ReLU(),
                nn.AdaptiveAvgPool2d(1), nn.Flatten(),
            )
            self.head = nn.Sequential(nn.Linear(32 * len(self.images) + n_state, 128), nn.ReLU(), nn.Linear(128, n_action))
            self.encoder.eval()
            self.head.eval()

        def reset(self) -> None:
            pass

        def select_action(self, observation) -> np.ndarray:
            with torch.inference_mode():
                state = torch.from_numpy(observation["observation.state"]).unsqueeze(0)
                feats = [self.encoder(torch.from_numpy(observation[k]).permute(2, 0, 1).unsqueeze(0).float() / 255)
                         for k in self.images]
                out = self.head(torch.cat([*feats, state], dim=1))
            # Small moves around the current joints: the arm stays in a sensible pose.
            return observation["observation.state"].astype(np.float64) + 0.01 * np.tanh(out.squeeze(0).numpy())

    torch.set_num_threads(1)
    return SmallPolicy()


def _env_step_ms(cameras: tuple[str, ...], steps: int) -> float:
    from teleop.gym import make_env

    env = make_env("lift", "panda", control_hz=HZ, cameras=cameras, image_size=SIZE, action="joint", max_seconds=1e6)
    try:
        obs, _ = env.reset(seed=1000)
        hold = obs["observation.state"].astype(np.float64)
        for _ in range(5):
            env.step(hold)
        times = []
        for _ in range(steps):
            t0 = time.perf_counter()
            env.step(hold)
            times.append(time.perf_counter() - t0)
        return 1000 * statistics.median(times)
    finally:
        env.close()


def measure(quick: bool = False) -> dict[str, float]:
    from teleop.learn.evaluate import EvalOptions, evaluate

    policy = _small_policy()
    timed: list[float] = []
    inner = policy.select_action

    def select_action(observation):
        t0 = time.perf_counter()
        action = inner(observation)
        timed.append(time.perf_counter() - t0)
        return action

    policy.select_action = select_action
    episodes = 3 if quick else 7
    summary = evaluate(policy, EvalOptions(scene="lift", robot="panda", episodes=episodes, seed=1000, max_seconds=2.0,
                                           control_hz=HZ, action="joint", cameras=CAMERAS, image_size=SIZE))
    rates = [e.steps / e.wall_seconds for e in summary.per_episode if e.wall_seconds > 0]
    steps = 100 if quick else 300
    return {
        "eval_steps_per_s": round(statistics.median(rates), 1),
        "eval_policy_ms": round(1000 * statistics.median(timed), 3),
        "env_step_ms": round(_env_step_ms(CAMERAS, steps), 3),
        "env_step_no_images_ms": round(_env_step_ms((), steps), 3),
    }
