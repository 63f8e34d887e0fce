"""`--robot.view=true`: this tool's session page on the LeRobot robot's own simulation, watch-only.

LeRobot's loop steps the simulation (one `send_action`, one tick); the page only shows it. So the page's control
loop is never started: each tick runs through its `step_once` in LeRobot's thread with the action as the only
device (`ActionFeed`), which keeps the page's snapshot, scene drawing, panel figures and status as `teleop serve`
has them. No device of the page drives: no gizmo, no page keys, no XR page, the panel's buttons and sliders
disabled (and the panel's own device not polled). Served on 127.0.0.1 unless asked (the token rule of
teleop/web/shared/access.py for any other host); its URL goes to stderr.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence

from devices.command import Command
from teleop.control.session import Session
from teleop.web.session_page.app import WebApp
from teleop.web.session_page.serve_options import ServeOptions

log = logging.getLogger(__name__)


class ActionFeed:
    """The commands LeRobot's action made for the next tick, as a device the page's loop polls once."""

    kind = "lerobot"

    def __init__(self) -> None:
        self.name = "lerobot"
        self.pending: list[Command] = []

    def start(self) -> None:
        """Nothing to open."""

    def poll(self, view, dt: float) -> list[Command]:
        out, self.pending = self.pending, []
        return out

    def status(self) -> str:
        return "driven by LeRobot"

    @property
    def finished(self) -> bool:
        return False

    def close(self) -> None:
        self.pending = []


class WatchPage:
    """The session page serving `session` without driving it; `step` is the robot's tick."""

    def __init__(self, session: Session, host: str = "127.0.0.1", port: int = 0) -> None:
        self.feed = ActionFeed()
        options = ServeOptions(host=host, port=port, page_keyboard=False, companions=())
        self.app = WebApp(session, [self.feed], [], options, camera=False, log=lambda line: log.warning("mujoco_teleop view: %s", line))
        self.app.sim.devices = [self.feed]  # not the panel's device: nothing on the page drives
        panel = self.app.panel
        for control in (panel.record_btn, panel.save_btn, panel.discard_btn, panel.reset_btn, panel.pos_slider, panel.rot_slider,
                        *(b for pair in panel.gripper_buttons for b in pair)):
            control.disabled = True
        self.app.drawer.start()
        self.app.panel.start()
        log.warning("mujoco_teleop: watch the simulation at %s", self.app.page_url)

    @property
    def url(self) -> str:
        """The page to open (with its token where one is needed)."""
        return self.app.page_url

    def step(self, commands: Sequence[Command]) -> None:
        """One control tick of the session under `commands`, drawn on the page."""
        self.feed.pending = list(commands)
        self.app.sim.step_once()

    def close(self) -> None:
        """Stop serving; the session is the robot's to close."""
        self.app.panel.stop()
        self.app.drawer.stop()
        self.app.server.stop()
