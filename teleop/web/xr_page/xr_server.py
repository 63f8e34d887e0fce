"""The XR page's parts for one served session: the `xr` device, its websocket, the page, the haptics' forces.

The session app (teleop/web/session_page/app.py) makes one `XrServer` before its control loop, adds
`device` to the loop's devices, serves `page()` at PAGE_PATH and `channel.handle` at CHANNEL_PATH, and
calls `tick()` after every control tick (on the loop's thread, where the physics may be read).
"""

from __future__ import annotations

from pathlib import Path

import mujoco
import numpy as np

from teleop.web.xr_page.scene_message import scene_message
from teleop.web.xr_page.xr_channel import PATH as CHANNEL_PATH
from teleop.web.xr_page.xr_channel import XrChannel, XrFrame
from teleop.web.xr_page.xr_device import XrDevice

PAGE_PATH = "/xr"
HERE = Path(__file__).parent
FORCE_CLIP_N = 20.0  # finger contact force (N) at which the controller's pulse is strongest (docs/xr.md)
__all__ = ["CHANNEL_PATH", "FORCE_CLIP_N", "PAGE_PATH", "XrServer", "finger_forces", "page"]


def page() -> bytes:
    """The XR page: xr.html with its script (xr.js) and the force clip put in."""
    html = (HERE / "xr.html").read_text(encoding="utf-8")
    script = (HERE / "xr.js").read_text(encoding="utf-8")
    return html.replace("/*XR_SCRIPT*/", script.replace("/*FORCE_CLIP_N*/20", repr(FORCE_CLIP_N))).encode("utf-8")


def finger_bodies(model: mujoco.MjModel, hand_bodies: tuple[str, ...]) -> set[int]:
    """Body ids of an arm's fingers (its hand bodies named `...finger...`; all its hand bodies if none is)."""
    names = [name for name in hand_bodies if "finger" in name] or list(hand_bodies)
    ids = (mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, name) for name in names)
    return {i for i in ids if i >= 0}


def finger_forces(model: mujoco.MjModel, data: mujoco.MjData, arms: list[set[int]]) -> np.ndarray:
    """Each arm's sum of its fingers' contact normal forces now (N); contacts between two of its fingers are left out."""
    forces = np.zeros(len(arms))
    if not data.ncon:
        return forces
    wrench = np.zeros(6)
    b1 = model.geom_bodyid[data.contact.geom1[:data.ncon]]
    b2 = model.geom_bodyid[data.contact.geom2[:data.ncon]]
    for i in range(data.ncon):
        for a, fingers in enumerate(arms):
            one, two = int(b1[i]) in fingers, int(b2[i]) in fingers
            if one != two:
                mujoco.mj_contactForce(model, data, i, wrench)
                forces[a] += abs(float(wrench[0]))
    return forces


class XrServer:
    """The XR page as a companion of a served session (ServeOptions.companions): its device, page, websocket and
    the per-tick frame it streams."""

    key = "xr"  # its entry in the session's status

    def __init__(self, n_arms: int) -> None:
        self.device = XrDevice(n_arms=n_arms)
        self.channel = XrChannel(self.device, self._scene, self._panel)
        self.pages = {PAGE_PATH: page()}
        self.routes = {CHANNEL_PATH: self.channel.handle}
        self._scenes: dict[int, bytes] = {}
        self._sources: dict[int, tuple[mujoco.MjModel, list]] = {}
        self._fingers: tuple[object, list[set[int]]] | None = None
        self._panel_state: dict = {}

    def _scene(self, generation: int) -> bytes:
        if generation not in self._scenes:
            model, bases = self._sources[generation]
            self._scenes = {generation: scene_message(model, bases, len(bases))}
        return self._scenes[generation]

    def _panel(self) -> dict:
        return self._panel_state

    def tick(self, controller, snapshot, problems: dict) -> None:
        """After a control tick, on the loop's thread: the bodies' poses, finger forces and the panel for the pages."""
        model, data, generation = controller.model, controller.data, snapshot.generation
        if generation not in self._sources:
            bases = [controller.base_pose(i) for i in range(controller.n_arms)]
            self._sources = {generation: (model, bases)}
        if self._fingers is None or self._fingers[0] is not model:
            self._fingers = (model, [finger_bodies(model, arm.hand_bodies) for arm in controller.scene.arms])
        forces = finger_forces(model, data, self._fingers[1])
        self._panel_state = {"recording": snapshot.recording, "episode_s": round(snapshot.episode_steps * controller.dt, 1),
                             "success": snapshot.success, "seed": snapshot.seed, "saved": snapshot.episodes_saved,
                             "lost": sorted(problems)}
        self.channel.tick(XrFrame(snapshot.tick, generation, float(data.time), data.xpos.copy(), data.xquat.copy(), forces,
                                  np.asarray(snapshot.tracking_error_m, dtype=float).copy()))

    def status(self) -> dict:
        return self.channel.status()

