"""A task scene as LeRobot's evaluation reads an env: `agent_pos`, `environment_state`, `pixels` (issue 58).

`teleop.learn.gym_env.TeleopEnv` observes with this tool's export keys (`observation.state`,
`observation.images.<cam>`), which LeRobot's `preprocess_observation` would misread (it renames every
key it does not know to `observation.<key>`, so `observation.observation.state`, and passes such images on
without their HWC -> CHW and /255 conversion). This wrapper renames them to LeRobot's conventions:

  agent_pos          -> observation.state              joints and grippers (rad, 1 open .. 0 closed)
  environment_state  -> observation.environment_state  each task object's pose in the robot's base frame
  ee_pose            -> observation.ee_pose            each arm's EE pose (m, wxyz; world)
  pixels/<cam>       -> observation.images.<cam>       (H, W, 3) uint8

so a policy trained on `teleop export` data is evaluated on what it was trained on (the same
vectors, computed by the same code). The task's instruction is `task` / `task_description`; success is
`info["is_success"]`; `make_lerobot_env` adds the `TimeLimit` lerobot-eval reads (`_max_episode_steps`).
"""

from __future__ import annotations

from fractions import Fraction
from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from gymnasium.wrappers import TimeLimit

from replay.features import ENV_STATE, feature_key
from teleop.learn.gym_env import TeleopEnv

STATE_KEYS = {"agent_pos": "observation.state", "environment_state": ENV_STATE, "ee_pose": "observation.ee_pose"}
PIXELS = "pixels"


def pixel_key(camera: str) -> str:
    """The `pixels` dict's key of a scene camera: LeRobot makes it `observation.images.<key>`, as the export names it."""
    return feature_key(camera).removeprefix("observation.images.")


class LeRobotKeys(gymnasium.ObservationWrapper):
    """TeleopEnv observed under LeRobot's keys (see the module docstring); actions and rewards unchanged."""

    def __init__(self, env: TeleopEnv) -> None:
        super().__init__(env)
        inner = env.observation_space
        obs: dict[str, spaces.Space] = {k: inner[v] for k, v in STATE_KEYS.items() if v in inner.spaces}
        if env.cameras:
            obs[PIXELS] = spaces.Dict({pixel_key(c): inner[feature_key(c)] for c in env.cameras})
        self.observation_space = spaces.Dict(obs)
        # LeRobot writes its eval videos with PyAV, whose frame rate must be an int or a Fraction (a float fails in
        # the writer's thread, silently: no video)
        rate = Fraction(env.session.control_hz).limit_denominator(1000)
        self.metadata = {**env.metadata, "render_fps": int(rate) if rate.denominator == 1 else rate}
        self.task = env.session.scene.instruction
        self.task_description = self.task

    def observation(self, observation: dict[str, np.ndarray]) -> dict[str, Any]:
        out: dict[str, Any] = {k: observation[v] for k, v in STATE_KEYS.items() if v in observation}
        if self.env.unwrapped.cameras:
            out[PIXELS] = {pixel_key(c): observation[feature_key(c)] for c in self.env.unwrapped.cameras}
        return out


def make_lerobot_env(task: str, robot: str, *, fps: float, cameras: list[str], image_size: tuple[int, int],
                     episode_length: int, action: str = "joint", render_mode: str | None = "rgb_array") -> gymnasium.Env:
    """One env as lerobot-eval steps it: LeRobot's keys, `episode_length` steps at most (TimeLimit)."""
    env = TeleopEnv(task, robot, control_hz=float(fps), cameras=cameras, image_size=image_size, action=action,
                    max_seconds=episode_length / float(fps), render_mode=render_mode)
    return TimeLimit(LeRobotKeys(env), max_episode_steps=int(episode_length))
