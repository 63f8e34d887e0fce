"""`--env.type=mujoco_teleop`: a task scene for `lerobot-eval` and `lerobot-train`'s evaluation (its config;
the env is lerobot_env.py). Imported by teleop.lerobot_plugin once `lerobot.envs.configs` is loaded.

`features` / `features_map` are those of the dataset `teleop export` writes for the same task, robot,
cameras, image size and action mode (computed from the scene when the config is made), so that
`env_to_policy_features` gives a policy the inputs it was trained on.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import partial

from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig

from teleop.lerobot_plugin import ENV_TYPE
from teleop.lerobot_plugin.options import OBS_TYPES, check_choice, check_rate, parse_camera_list, parse_image_size

EXPORT_ACTIONS = ("joint", "ee_delta", "ee_pose")
KINDS = {"agent_pos": FeatureType.STATE, "environment_state": FeatureType.ENV, "ee_pose": FeatureType.STATE}


@EnvConfig.register_subclass(ENV_TYPE)
@dataclass
class MujocoTeleopEnvConfig(EnvConfig):
    """task: a library task name or a task file PATH.toml; robot: a built-in robot or a PATH.toml; fps: control
    ticks a second (the export's); cameras: comma-separated scene cameras (None: `front` with obs_type
    pixels_agent_pos, none with state); image_size: WIDTHxHEIGHT; episode_length: steps before truncation;
    obs_type: state (joints, objects, EE pose) or pixels_agent_pos (those and the cameras); action: the
    export's action mode the policy was trained with (joint | ee_delta | ee_pose)."""

    task: str | None = "lift"
    robot: str = "panda"
    fps: int = 30
    cameras: str | None = None
    image_size: str = "96x96"
    episode_length: int = 300
    obs_type: str = "state"
    action: str = "joint"
    render_mode: str = "rgb_array"
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_choice("obs_type", self.obs_type, OBS_TYPES)
        check_choice("action", self.action, EXPORT_ACTIONS)
        check_rate("fps", self.fps)
        parse_image_size(self.image_size)
        if isinstance(self.episode_length, bool) or not isinstance(self.episode_length, int) or self.episode_length < 1:
            raise ValueError(f"episode_length must be a whole number of steps >= 1 (got {self.episode_length!r})")
        if not self.features:
            self.features, self.features_map = self._features()

    @property
    def camera_names(self) -> list[str]:
        if self.cameras is None:
            return ["front"] if self.obs_type == "pixels_agent_pos" else []
        return parse_camera_list(self.cameras)

    def _options(self, render_mode: str | None) -> dict:
        return {"fps": self.fps, "cameras": self.camera_names, "image_size": parse_image_size(self.image_size),
                "episode_length": self.episode_length, "action": self.action, "render_mode": render_mode}

    def _features(self) -> tuple[dict[str, PolicyFeature], dict[str, str]]:
        """The export's features, read off one env of this config (built, never stepped nor rendered)."""
        from teleop.lerobot_plugin.lerobot_env import PIXELS, STATE_KEYS, make_lerobot_env

        env = make_lerobot_env(self.task, self.robot, **self._options(None))
        try:
            space = env.observation_space
            features = {"action": PolicyFeature(type=FeatureType.ACTION, shape=tuple(env.action_space.shape))}
            mapping = {"action": "action"}
            for key, box in space.spaces.items():
                if key == PIXELS:
                    for cam, image in box.spaces.items():
                        features[f"{PIXELS}/{cam}"] = PolicyFeature(type=FeatureType.VISUAL, shape=tuple(image.shape))
                        mapping[f"{PIXELS}/{cam}"] = f"observation.images.{cam}"
                else:
                    features[key] = PolicyFeature(type=KINDS[key], shape=tuple(box.shape))
                    mapping[key] = STATE_KEYS[key]
        finally:
            env.close()
        return features, mapping

    @property
    def gym_kwargs(self) -> dict:
        return {"task": self.task, "robot": self.robot, **self._options(self.render_mode)}

    def create_envs(self, n_envs: int, use_async_envs: bool = False):
        """{"mujoco_teleop": {0: VectorEnv}} of `n_envs` envs (not through gym.make: no gym_<type> package).

        Each env is wrapped in LeRobot's `FreezeAfterEpisodeEnd`, as its own lazy async envs are: the vector env's
        autoreset after an episode's last step would otherwise build the next seed's scene only for the rollout
        to build it again at its own reset (one scene build an episode, ~50 ms, as `teleop eval` does)."""
        import gymnasium as gym
        from lerobot.envs.utils import freeze_after_episode_end

        from teleop.lerobot_plugin.lerobot_env import make_lerobot_env

        make_one = freeze_after_episode_end(partial(make_lerobot_env, **self.gym_kwargs))
        if use_async_envs and n_envs > 1:
            vec = gym.vector.AsyncVectorEnv([make_one] * n_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP,
                                            context="forkserver")
        else:
            vec = gym.vector.SyncVectorEnv([make_one] * n_envs, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
        return {self.type: {0: vec}}
