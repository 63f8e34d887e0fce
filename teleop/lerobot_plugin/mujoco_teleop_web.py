"""`--teleop.type=mujoco_teleop_web`: this tool's browser page as a LeRobot teleoperator.

The page (gizmo, keys, gamepad, phone, SpaceMouse: `teleop serve`'s devices) drives its own simulated arm
(`scene`, `robot`) through this tool's IK; `get_action` returns that arm's joint targets, keyed and scaled like
the robot it drives (teleop/lerobot_plugin/units.py): `<joint>.pos` in degrees and `gripper.pos` 0..100 for the
so101, so `lerobot-teleoperate --robot.type=so101_follower` moves a real SO-101 and `--robot.type=mujoco_teleop`
the simulated one. The page's simulation runs at `fps` on its own thread; LeRobot's loop reads its latest targets.

The two loops share no lock: after every tick the simulation's thread publishes that tick's targets as one new
dict (a tick hook), and `get_action` returns the newest one, so LeRobot's loop never waits on the simulation (a
real arm's bus keeps its timing) and never reads a tick half written. The status file (`status_file`) carries the
same action as `lerobot_action` (`tick`, `values`), for scripts that compare what the arm was sent. If the page's
simulation stops on an error, `get_action` raises it: LeRobot's loop ends instead of holding a frozen target.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from lerobot.teleoperators.teleoperator import Teleoperator
from lerobot.utils.errors import DeviceAlreadyConnectedError, DeviceNotConnectedError

from devices.registry import SERVE_DEVICES, DeviceOptions, open_devices
from teleop.learn.gym_env import TeleopEnv
from teleop.lerobot_plugin.config_mujoco_teleop_web import MujocoTeleopWebConfig
from teleop.lerobot_plugin.units import RobotUnits
from teleop.web.session_page.app import WebApp, status_text
from teleop.web.session_page.serve_options import ServeOptions

log = logging.getLogger(__name__)


class MujocoTeleopWeb(Teleoperator):
    """The browser page's IK joint targets for the simulated `robot`, as LeRobot actions."""

    config_class = MujocoTeleopWebConfig
    name = "mujoco_teleop_web"

    def __init__(self, config: MujocoTeleopWebConfig) -> None:
        super().__init__(config)
        self.config = config
        self.env = TeleopEnv(config.scene, config.robot, control_hz=float(config.fps), cameras=[], seed=0, object_state=False)
        self.units = RobotUnits.of(self.env.features["observation.state"]["names"],
                                   [n for arm in self.env.arms for n in arm.gripper_name], self.env.session.robot.name)
        self.app: WebApp | None = None
        self._published: tuple[int, dict[str, float]] = (0, self._targets(self.env.session.controller))

    @property
    def action_features(self) -> dict[str, type]:
        return {k: float for k in self.units.keys}

    @property
    def feedback_features(self) -> dict:
        return {}

    @property
    def is_connected(self) -> bool:
        return self.app is not None

    @property
    def is_calibrated(self) -> bool:
        return True

    def calibrate(self) -> None:
        """A page needs none."""

    def configure(self) -> None:
        """Nothing to configure."""

    def connect(self, calibrate: bool = True) -> None:
        """Serve the page (its URL on stderr) and start its simulation."""
        if self.app is not None:
            raise DeviceAlreadyConnectedError(f"{self} is already connected")
        session = self.env.session
        options = ServeOptions(host=self.config.host, port=self.config.port, status_file=self.config.status_file,
                               status_form=self._status_text)
        devices, problems = open_devices(",".join(SERVE_DEVICES), DeviceOptions(n_arms=session.controller.n_arms), require_any=False)
        app = WebApp(session, devices, problems, options, log=lambda line: log.warning("mujoco_teleop_web: %s", line))
        self._published = (0, self._targets(session.controller))
        app.sim.tick_hooks.append(self._publish)
        app.start()
        self.app = app
        log.warning("mujoco_teleop_web: drive the arm at %s", app.page_url)

    @property
    def url(self) -> str:
        """The page to open (with its token where one is needed)."""
        if self.app is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        return self.app.page_url

    def get_action(self) -> dict[str, float]:
        """The page's simulated arm's joint targets (its IK's output) and gripper after its newest tick, in the
        driven robot's units; RuntimeError once the page's simulation has stopped on an error."""
        app = self.app
        if app is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        if app.sim.error is not None:
            raise RuntimeError(f"mujoco_teleop_web: the page's simulation stopped ({app.sim.error})")
        return dict(self._published[1])

    def _targets(self, controller) -> dict[str, float]:
        """The joint targets in `controller`'s ctrl (radians) and each gripper's opening, in the driven robot's units."""
        ctrl = np.array(controller.data.ctrl, dtype=np.float64)
        values: list[float] = []
        for arm in self.env.arms:
            values += ctrl[arm.ctrl_ids].tolist()
            if arm.gripper_id is not None:
                values.append(min(max(arm.gripper_fraction(ctrl[arm.gripper_id]), 0.0), 1.0))
        return self.units.to_lerobot(values)

    def _publish(self, controller, snapshot, device_problems) -> None:
        """A tick hook (the simulation's thread, after each tick): that tick's targets, swapped in whole."""
        self._published = (snapshot.tick, self._targets(controller))

    def _status_text(self, status: dict) -> str:
        """The page's status file, with the action LeRobot reads now (`lerobot_action`: its tick and values)."""
        tick, values = self._published
        return status_text({**status, "lerobot_action": {"tick": tick, "values": values}})

    def send_feedback(self, feedback: dict[str, Any]) -> None:
        """The page takes none."""

    def disconnect(self) -> None:
        if self.app is None:
            raise DeviceNotConnectedError(f"{self} is not connected")
        app, self.app = self.app, None
        app.close()
        self.env.close()

