"""`--robot.type=mujoco_teleop`: the simulation as a LeRobot `Robot` that LeRobot's own commands drive.

One `send_action` is one control tick (1/fps s of simulated time, whatever the loop's pace); one
`get_observation` is the live state as this tool's export reads it (teleop.learn.gym_env.TeleopEnv):
`<joint>.pos` per joint and gripper (units: teleop/lerobot_plugin/units.py; the so101 in so101_follower's)
and `<camera>` images (H, W, 3) uint8 rendered from the simulation.

Episodes. LeRobot has no reset call for a robot, so the simulation follows the dataset: when `lerobot-record`
saves an episode (`LeRobotDataset.save_episode`, after its reset period) the scene moves at once to the next
seed's initial state (seed, seed + 1, ...); when it re-records one (`clear_episode_buffer`) the same seed
starts again from its initial state. The reset happens there, between LeRobot's loops, so the new episode's
clock does not pay for it. The reset period itself runs on in the scene that just ended (nothing is recorded
then). So every recorded episode starts at its seed's initial state and never where the last one ended.
Without a dataset (lerobot-teleoperate) the scene simply runs on.
"""

from __future__ import annotations

import functools
import logging
import weakref
from pathlib import Path
from typing import Any

import numpy as np
from lerobot.robots.robot import Robot
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from devices.command import Command
from replay.features import feature_key
from teleop.learn.gym_env import TeleopEnv
from teleop.lerobot_plugin.config_mujoco_teleop import MujocoTeleopConfig
from teleop.lerobot_plugin.options import parse_camera_list, parse_image_size
from teleop.lerobot_plugin.units import RobotUnits

log = logging.getLogger(__name__)
EE_DELTA_KEYS = ("delta_x", "delta_y", "delta_z", "gripper")
# LeRobot's keyboard_ee / gamepad gripper values (GripperAction): 0 close, 1 stay, 2 open
GRIPPER_CLOSE, GRIPPER_OPEN = 0.5, 1.5  # below: close; above: open; between: no change
NEXT, SAME = "next", "same"
_LIVE: weakref.WeakSet[MujocoTeleop] = weakref.WeakSet()


def _follow_datasets() -> None:
    """Tell connected simulations when LeRobot saves or re-records an episode (once per process)."""
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    if getattr(LeRobotDataset.save_episode, "_mujoco_teleop", False):
        return
    save, clear = LeRobotDataset.save_episode, LeRobotDataset.clear_episode_buffer

    @functools.wraps(save)
    def save_episode(self, *args, **kwargs):
        out = save(self, *args, **kwargs)
        for robot in list(_LIVE):
            robot.episode_ended(NEXT)
        return out

    @functools.wraps(clear)
    def clear_episode_buffer(self, *args, **kwargs):
        out = clear(self, *args, **kwargs)
        for robot in list(_LIVE):
            robot.episode_ended(SAME)
        return out

    save_episode._mujoco_teleop = clear_episode_buffer._mujoco_teleop = True
    LeRobotDataset.save_episode, LeRobotDataset.clear_episode_buffer = save_episode, clear_episode_buffer


def image_key(camera: str) -> str:
    """LeRobot's key of a scene camera (`left/wrist` -> `left_wrist`): the dataset has observation.images.<key>."""
    return feature_key(camera).removeprefix("observation.images.")


class MujocoTeleop(Robot):
    """A simulated arm (or two) in a task scene; features are known before `connect` (the scene is built here)."""

    config_class = MujocoTeleopConfig
    name = "mujoco_teleop"

    def __init__(self, config: MujocoTeleopConfig) -> None:
        super().__init__(config)
        self.config = config
        width, height = parse_image_size(config.image_size)
        self.env = TeleopEnv(config.scene, config.robot, control_hz=float(config.fps), cameras=parse_camera_list(config.cameras),
                             image_size=(width, height), action="joint", seed=config.seed, object_state=False, max_seconds=1e9)
        self.units = RobotUnits.of(self.env.features["observation.state"]["names"],
                                   [n for arm in self.env.arms for n in arm.gripper_name], self.env.session.robot.name)
        self.cameras = {image_key(c): c for c in self.env.cameras}  # lerobot-record counts them
        self._image_shape = (height, width, 3)
        self.episode = 0  # episodes saved since connect: the running one's seed is config.seed + episode
        self._connected = False
        self.recorder = None
        self.view = None  # the watch-only page (teleop.lerobot_plugin.watch_page.WatchPage) with view=true

    # --- features ------------------------------------------------------------

    @property
    def observation_features(self) -> dict[str, Any]:
        return {**{k: float for k in self.units.keys}, **{k: self._image_shape for k in self.cameras}}

    @property
    def action_features(self) -> dict[str, Any]:
        if self.config.action_space == "ee_delta":
            return {k: float for k in EE_DELTA_KEYS}
        return {k: float for k in self.units.keys}

    # --- lifecycle -----------------------------------------------------------

    @property
    def is_connected(self) -> bool:
        return self._connected

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """A simulation needs none."""

    def configure(self) -> None:
        """Nothing to configure."""

    def connect(self, calibrate: bool = True) -> None:
        """The first episode's scene (config.seed) and this tool's recorder where asked."""
        if self._connected:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        self.env.reset(seed=self.config.seed)
        self.env.observe()  # the renderer's GL context is made here, not in the first episode's clock
        if self.config.record_dir is not None:
            from teleop.control.recording import Recorder

            self.recorder = Recorder(self.env.session, Path(self.config.record_dir), formats=(self.config.record_format,))
            self.recorder.devices = ("lerobot",)
            self.recorder.start()
        if self.config.view:
            from teleop.lerobot_plugin.watch_page import WatchPage

            self.view = WatchPage(self.env.session, self.config.view_host, self.config.view_port)
        _follow_datasets()
        _LIVE.add(self)
        self._connected = True

    def disconnect(self) -> None:
        """Free the renderer; this tool's open episode is kept, marked incomplete (LeRobot never saved it), or
        dropped when it has no step (the one begun after LeRobot's last save)."""
        if not self._connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        _LIVE.discard(self)
        self._connected = False
        if self.view is not None:
            self.view.close()
            self.view = None
        if self.recorder is not None:
            if self.recorder.recording:
                if self.recorder.steps == 0:
                    self.recorder.discard()
                else:
                    self.recorder.save(complete=False)
            self.env.session.detach(self.recorder)
        self.env.close()

    # --- episodes ------------------------------------------------------------

    @property
    def seed(self) -> int:
        """The scene seed of the episode running now."""
        return self.env.session.seed

    def episode_ended(self, how: str) -> None:
        """LeRobot saved (NEXT) or dropped (SAME) an episode: the next one starts now, at its seed's initial state."""
        if how == NEXT:
            self.episode += 1
        elif self.recorder is not None and self.recorder.recording:
            self.recorder.discard()
        self.env.reset(seed=self.config.seed + self.episode)  # saves this tool's episode in progress first
        self.env.observe()
        if self.recorder is not None:
            self.recorder.start()

    # --- the loop ------------------------------------------------------------

    def get_observation(self) -> dict[str, Any]:
        if not self._connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        obs = self.env.observe()
        out: dict[str, Any] = self.units.to_lerobot(obs["observation.state"])
        for key, camera in self.cameras.items():
            out[key] = obs[feature_key(camera)]
        return out

    def send_action(self, action: dict[str, Any]) -> dict[str, Any]:
        """One control tick under `action`; returns the action as applied (joints clamped to their ranges)."""
        if not self._connected:
            raise DeviceNotConnectedError(f"{self} is not connected")
        if self.config.action_space == "ee_delta":
            commands, sent = self._ee_delta(action)
        else:
            commands, sent = self._joints(action)
        if self.view is not None:
            self.view.step(commands)  # the same tick, drawn on the watch-only page
        else:
            self.env.session.step(commands)
        return sent

    def _joints(self, action: dict[str, Any]) -> tuple[list[Command], dict[str, float]]:
        values = self.units.from_lerobot(action)
        model, commands, i = self.env.model, [], 0
        applied = []
        for k, arm in enumerate(self.env.arms):
            n = len(arm.joints)
            q = np.array(values[i:i + n], dtype=np.float64)
            for j, joint in enumerate(arm.joints):
                jid = model.joint(joint).id
                if model.jnt_limited[jid]:
                    q[j] = np.clip(q[j], *model.jnt_range[jid])
            applied += list(q)
            i += n
            opening = None
            if arm.gripper_id is not None:
                opening = float(np.clip(values[i], 0.0, 1.0))
                applied.append(opening)
                i += 1
            commands.append(Command(joints=q, gripper_opening=opening, arm=k, source="lerobot"))
        return commands, self.units.to_lerobot(applied)

    def _ee_delta(self, action: dict[str, Any]) -> tuple[list[Command], dict[str, float]]:
        try:
            delta = np.array([float(action[k]) for k in EE_DELTA_KEYS[:3]], dtype=np.float64)
        except KeyError as exc:
            raise ValueError(f"the action lacks {exc.args[0]} (ee_delta actions: {', '.join(EE_DELTA_KEYS)})") from None
        if not np.all(np.isfinite(delta)):
            raise ValueError("the action's delta_x/y/z are not all finite numbers")
        grip = float(action.get("gripper", 1.0))
        gripper = "close" if grip < GRIPPER_CLOSE else "open" if grip > GRIPPER_OPEN else None
        command = Command(translation=delta * self.config.ee_step_m, frame="world", gripper=gripper, arm=0, source="lerobot")
        return [command], {**{k: float(action[k]) for k in EE_DELTA_KEYS[:3]}, "gripper": grip}

