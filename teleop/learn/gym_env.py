"""A task scene as a Gymnasium environment, observed and driven as the export records it.

Observations and actions are the LeRobot export's (replay/features.py):
the same feature names and vector layouts, computed the same way. Each
observation restores the session's state into a scratch MjData and
mj_forward-s it, as the export replays a recorded state, then builds the
vectors with the export's `FrameBuilder` and renders the cameras with its
`FastRenderer`; so a policy trained on an export sees at run time what it
was trained on. One step is one control tick (1/control_hz s).

Actions, per arm in recorded order, concatenated (`features["action"]["names"]`):

  joint     joint position targets (rad, or m for slide joints), then gripper
  ee_pose   EE target position (m, world) and wxyz quaternion, then gripper
  ee_delta  EE target minus the current EE pose: position (m, world) and
            rotation vector (rad, world frame), then gripper

The gripper entry is 1 = open .. 0 = closed, and opens at >= 0.5. Joint
targets go straight into ctrl (no IK): a recorded episode's ctrl, given as
float64, replays bit for bit. EE actions go through the session's workspace
clamp and IK, as a device's commands do.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import gymnasium
import mujoco
import numpy as np

from devices.command import Command
from replay.episode import EpisodeMeta
from replay.features import (
    ACTION_MODES, DEFAULT_CAMERAS, ENV_STATE, ArmLayout, CameraChoiceError, FrameBuilder, ObjectLayout, feature_key, object_layout,
    parse_cameras, resolve_cameras, robot_layout,
)
from replay.render import FastRenderer
from scenes import RobotSpec
from scenes.vary.variation import Variation, eval_look_seed, looks_kinds, task_ranges
from scenes.vary.looks import apply_looks, sample_looks
from teleop.errors import EnvError
from teleop.learn.gym_spaces import make_spaces
from teleop.control.recording import arm_metas
from teleop.control.session import Session

INTEGRATION = mujoco.mjtState.mjSTATE_INTEGRATION
DEFAULT_IMAGE_SIZE = (224, 224)  # width, height, as the export
DEFAULT_MAX_SECONDS = 20.0
GRIPPER_OPENS_AT = 0.5  # on the 1 = open .. 0 = closed scale

Observation = dict[str, np.ndarray]


def _image_size(size: int | Sequence[int]) -> tuple[int, int]:
    """(width, height) in pixels; an int is a square."""
    pair = [size, size] if isinstance(size, (int, np.integer)) else list(size) if isinstance(size, (tuple, list)) else []
    if len(pair) != 2 or not all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) and 0 < v <= 4096 for v in pair):
        raise EnvError(f"image size {size!r}: expected (width, height) in pixels, 1 to 4096 each")
    return int(pair[0]), int(pair[1])


def _check_options(action: str, max_seconds: float, seed: int, render_mode: str | None) -> None:
    if action not in ACTION_MODES:
        raise EnvError(f"action {action!r}: choose one of {', '.join(ACTION_MODES)}")
    if not (isinstance(max_seconds, (int, float)) and math.isfinite(max_seconds) and max_seconds > 0):
        raise EnvError(f"max_seconds must be a positive number of seconds, got {max_seconds!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise EnvError(f"seed must be a whole number >= 0, got {seed!r}")
    if render_mode not in (None, *TeleopEnv.metadata["render_modes"]):
        raise EnvError(f"render mode {render_mode!r}: choose rgb_array or none")


class TeleopEnv(gymnasium.Env[Observation, np.ndarray]):
    """A robot in a task scene; reward 1.0 and `terminated` on the task's success,
    `truncated` after `max_seconds` of simulated time.

    scene / robot / control_hz: as a `Session` (robot: a built-in name or a PATH.toml).
    cameras: names to observe (None: front and wrist where the scene has them, as
    the export; "wrist" means every arm's wrist camera); () observes no images.
    image_size: (width, height) in pixels. action: "joint", "ee_pose" or "ee_delta".
    object_state: observe `observation.environment_state` (each task object's position, m,
    and wxyz quaternion in the robot's base frame), as the export writes it by default.
    seed: the scene seed of the first reset without one; reset(seed=s) builds
    the scene for seed s, a reset without a seed the next seed.
    variation: physics drawn into each seed's scene, and looks (scenes.vary.looks) its cameras are
    rendered with, from the look seed `eval_look_seed(looks_seed, split)` and the scene seed
    (`variation_json()` says what each episode got).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        scene: str = "lift",
        robot: str | Path | RobotSpec = "panda",
        *,
        control_hz: float = 30.0,
        cameras: Sequence[str] | str | None = None,
        image_size: int | Sequence[int] = DEFAULT_IMAGE_SIZE,
        action: str = "joint",
        max_seconds: float = DEFAULT_MAX_SECONDS,
        seed: int = 0,
        render_mode: str | None = None,
        session: Session | None = None,
        object_state: bool = True,
        variation: Variation | None = None,
    ) -> None:
        _check_options(action, max_seconds, seed, render_mode)
        self.variation = variation
        self.look: dict | None = None  # the look the cameras are rendered with (None: the scene's own)
        self.image_size = _image_size(image_size)
        # session: observe and drive this live Session (a served one a policy drives) instead of
        # building one; scene, robot, control_hz and seed are then the session's.
        self.session = session if session is not None else Session(scene, robot, int(seed), control_hz, variation=variation)
        self.action_mode = action
        self.object_state = bool(object_state)
        self.render_mode = render_mode
        self.metadata = {**TeleopEnv.metadata, "render_fps": self.session.control_hz}
        self.max_steps = max(1, math.ceil(max_seconds * self.session.control_hz - 1e-9))
        have = list(self.session.scene.cameras)
        wanted = parse_cameras(cameras) if isinstance(cameras, str) else None if cameras is None else list(cameras)
        try:
            self.cameras = resolve_cameras(wanted, have)
        except CameraChoiceError as exc:
            raise EnvError(str(exc)) from None
        self.render_camera = (self.cameras or [c for c in (*DEFAULT_CAMERAS, *have) if c in have] or [""])[0]
        if render_mode is not None and not self.render_camera:
            raise EnvError(f"scene {scene!r} has no camera to render")
        self._next_seed = int(seed)
        self._renderer: FastRenderer | None = None
        self._renderer_model: mujoco.MjModel | None = None  # the model the renderer has loaded
        self._load()
        if render_mode is not None:  # the GL context (0.1-0.5 s on a CPU renderer) made with the env, not in its first episode
            self._renderer_for_images()
        self.features, self.observation_space, self.action_space = make_spaces(
            self.session.controller, self.arms, action, self.cameras, self.image_size, self.objects
        )
        self._steps = 0
        self._last_obs: Observation | None = None

    # --- the scene ---------------------------------------------------------

    @property
    def model(self) -> mujoco.MjModel:
        return self.session.controller.model

    @property
    def data(self) -> mujoco.MjData:
        """The live physics state (read it; change it through `set_state`)."""
        return self.session.controller.data

    def _load(self) -> None:
        """Per built scene: the arms' layout, the export's frame builder, a scratch MjData, the renderer's model."""
        controller = self.session.controller
        meta = EpisodeMeta(
            scene=self.session.scene_name, robot=controller.scene.robot.name, arms=arm_metas(controller),
            nstate=controller.nstate, nq=self.model.nq, nv=self.model.nv, nu=self.model.nu,
            control_hz=controller.control_hz, timestep=controller.timestep, substeps=controller.substeps,
        )
        self.arms: list[ArmLayout] = robot_layout(meta, self.model)
        self.objects: ObjectLayout | None = object_layout(meta, self.model) if self.object_state else None
        self._loaded_model = self.model
        self._frames = FrameBuilder(self.arms, self.action_mode, self.objects)  # new per episode: quaternion signs start afresh
        self._scratch = mujoco.MjData(self.model)
        self._state = np.empty(controller.nstate)
        self._render_model, self._render_data = self.model, self._scratch
        kinds = looks_kinds(self.variation.kinds, "eval") if self.variation is not None else ()
        self.look = None
        if kinds:  # another look: a model of its own to render, the same state restored into it
            variation, scene = self.variation, controller.scene
            ranges = variation.ranges(task_ranges(scene.task))
            joints = [j for arm in meta.arms for j in arm.joints]
            self.look = sample_looks(self.model, joints, ranges, kinds, eval_look_seed(variation.looks_seed, variation.split),
                                     self.session.seed)
            self._render_model = apply_looks(scene.xml, scene.assets, self.look, ranges.texture_data)
            self._render_data = mujoco.MjData(self._render_model)

    def _render_cameras(self) -> list[str]:
        extra = [self.render_camera] if self.render_mode and self.render_camera not in self.cameras else []
        return [*self.cameras, *extra]

    def _renderer_for_images(self) -> FastRenderer | None:
        """The export's renderer, made on first use (a GL context costs ~0.1 s; no cameras, none), with this
        episode's model loaded when first asked for in the episode (~17 ms: an episode nobody renders, as
        lerobot-eval's past the 10 it films, skips it)."""
        if self._renderer is None and self._render_cameras():
            self._renderer = FastRenderer(self._render_model, *self.image_size, self._render_cameras())
            self._renderer_model = self._render_model
        elif self._renderer is not None and self._renderer_model is not self._render_model:
            self._renderer.load(self._render_model)
            self._renderer_model = self._render_model
        return self._renderer

    def get_state(self) -> np.ndarray:
        """The live mjSTATE_INTEGRATION state, as episode files store each step's."""
        state = np.empty(self.session.controller.nstate)
        mujoco.mj_getState(self.model, self.data, state, INTEGRATION)
        return state

    def set_state(self, state: np.ndarray) -> Observation:
        """Restore a mjSTATE_INTEGRATION state of this scene (e.g. a recorded step's) and observe it.

        The EE targets follow the restored ctrl, so EE actions continue from there.
        """
        state = np.asarray(state, dtype=np.float64)
        if state.shape != (self.session.controller.nstate,):
            raise EnvError(f"state has shape {state.shape}, this scene's has ({self.session.controller.nstate},)")
        mujoco.mj_setState(self.model, self.data, state, INTEGRATION)
        mujoco.mj_forward(self.model, self.data)
        self.session.controller.follow_ctrl()
        return self._observe()

    # --- observations --------------------------------------------------------

    def observe(self) -> Observation:
        """The observation of the live state, whoever stepped it (a served session between ticks)."""
        if self.session.controller.model is not self._loaded_model:  # the session was reset: a new model
            self._load()
        return self._observe()

    def _observe(self) -> Observation:
        """The export's frame of the live state: restored into the scratch MjData, forward-computed."""
        mujoco.mj_getState(self.model, self.data, self._state, INTEGRATION)
        mujoco.mj_setState(self.model, self._scratch, self._state, INTEGRATION)
        mujoco.mj_forward(self.model, self._scratch)
        targets = np.array([np.concatenate(self.session.controller.target_pose(i)) for i in range(len(self.arms))])
        frame = self._frames(self._scratch, self._scratch.ctrl, targets)
        obs = {"observation.state": frame["observation.state"], "observation.ee_pose": frame["observation.ee_pose"]}
        if ENV_STATE in frame:
            obs[ENV_STATE] = frame[ENV_STATE]
        renderer = self._renderer_for_images() if self.cameras else None
        if self.cameras and self._render_data is not self._scratch:
            mujoco.mj_setState(self._render_model, self._render_data, self._state, INTEGRATION)
            mujoco.mj_forward(self._render_model, self._render_data)
        for c, cam in enumerate(self.cameras):
            obs[feature_key(cam)] = renderer.render(self._render_data, c)
        self._last_obs = obs
        return obs

    def variation_json(self) -> dict[str, Any] | None:
        """What this episode's scene varies: its physics (drawn into the model) and the look of its cameras; None: nothing."""
        physics = self.session.scene.variation or None
        if physics is None and self.look is None:
            return None
        return {"physics": physics, "looks": self.look}

    def _info(self, success: bool) -> dict[str, Any]:
        return {"is_success": success, "seed": self.session.seed, "time": self.session.controller.time}

    # --- gymnasium.Env -------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None) -> tuple[Observation, dict[str, Any]]:
        """Build the scene for `seed` (None: the next seed) and observe its first state."""
        super().reset(seed=seed)
        scene_seed = self._next_seed if seed is None else int(seed)
        self._next_seed = scene_seed + 1
        self.session.reset(scene_seed)
        self._load()
        self._steps = 0
        obs = self._observe()
        return obs, self._info(self.session.controller.success())

    def step(self, action: np.ndarray) -> tuple[Observation, float, bool, bool, dict[str, Any]]:
        """One control tick under `action` (kept in the caller's precision: float64 stays exact)."""
        action = np.asarray(action, dtype=np.float64)
        if action.shape != self.action_space.shape:
            raise EnvError(f"action has shape {action.shape}, expected {self.action_space.shape} ({self.action_mode})")
        if not np.all(np.isfinite(action)):
            raise EnvError("action has non-finite values")
        commands, ctrl = self.to_step(action)
        self.session.step(commands, ctrl=ctrl)
        self._steps += 1
        obs = self._observe()
        success = self.session.controller.success()
        truncated = self._steps >= self.max_steps
        return obs, 1.0 if success else 0.0, success, truncated, self._info(success)

    def render(self) -> np.ndarray | None:
        """The render camera's (H, W, 3) uint8 frame of the last observed state (rgb_array mode)."""
        if self.render_mode != "rgb_array":
            return None
        if self._last_obs is None:
            self._observe()
        if self.render_camera in self.cameras:
            return self._last_obs[feature_key(self.render_camera)].copy()
        if self._render_data is not self._scratch:
            mujoco.mj_setState(self._render_model, self._render_data, self._state, INTEGRATION)
            mujoco.mj_forward(self._render_model, self._render_data)
        return self._renderer_for_images().render(self._render_data, len(self.cameras))

    def close(self) -> None:
        """Free the renderer's GL context (safe to call twice)."""
        renderer, self._renderer, self._renderer_model = self._renderer, None, None
        if renderer is not None:
            renderer.close()
        super().close()

    # --- actions -------------------------------------------------------------

    def to_step(self, action: np.ndarray) -> tuple[list[Command], np.ndarray | None]:
        """What `Session.step` takes for `action`: (commands, None) for EE actions, ((), ctrl) for joint ones."""
        if self.action_mode == "joint":
            return [], self._joint_ctrl(action)
        return self._ee_commands(action), None

    def _joint_ctrl(self, action: np.ndarray) -> np.ndarray:
        """The whole ctrl vector for a joint action: joint targets as given, grippers open or closed."""
        ctrl = self.data.ctrl.copy()
        i = 0
        for arm in self.arms:
            n = len(arm.ctrl_ids)
            ctrl[arm.ctrl_ids] = action[i : i + n]
            i += n
            if arm.gripper_id is not None:
                opened = action[i] >= GRIPPER_OPENS_AT
                ctrl[arm.gripper_id] = arm.gripper_open if opened else arm.gripper_closed
                i += 1
        return ctrl

    def _ee_commands(self, action: np.ndarray) -> list[Command]:
        """One absolute-target Command per arm, as a device gives them."""
        commands = []
        i = 0
        for k, arm in enumerate(self.arms):
            if self.action_mode == "ee_pose":
                command = Command(target_pos=action[i : i + 3], target_quat=action[i + 3 : i + 7], arm=k, source="policy")
                i += 7
            else:  # ee_delta: the export's (target - actual) in the world frame, added back to the actual pose
                pos, quat = self.session.controller.ee_pose(k)
                command = Command(translation=action[i : i + 3], rotation=action[i + 3 : i + 6], target_pos=pos,
                                  target_quat=quat, frame="world", arm=k, source="policy")
                i += 6
            if arm.gripper_id is not None:
                command.gripper = "open" if action[i] >= GRIPPER_OPENS_AT else "close"
                i += 1
            commands.append(command)
        return commands
