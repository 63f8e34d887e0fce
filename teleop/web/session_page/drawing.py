"""The 3D view: the MuJoCo scene, target and actual end-effector markers, and the gizmos.

The camera's start and the markers (`place_camera`, `Markers`) are every 3D page's
(teleop.web.shared.camera_markers), so a recorded episode looks in the replay viewer as it did live.

Drawing never reads the physics MjData: it draws the body poses of the latest
Snapshot (copied at the end of a tick). It runs
in viser's event loop, cued by each tick of the control loop (at most `max_hz`
times a second, and only when the state changed): the poses go into mjviser's
batched handles (body_poses.BodyPoses), and they, the markers and the gizmos
go out as one frame written to each page from there (viser_internals.scene_stream.SceneStream).
Waking a thread costs ~0.1-0.25 ms of CPU on the project's virtual machine, a
good part of a session's cost when many run on one: a tick wakes the control
loop and viser's loop, and no drawing thread besides. (Drawing in the control
loop's own thread woke one thread less, but a tick twice as long waits longer
for a core when the machine is crowded: at 20 sessions the loops fell to half
real time.)

Gizmos are two-way. A drag pushes poses into the gizmo device; when the target
moves for any other reason (keyboard, SpaceMouse, a target clamped to the
workspace, a reset) the gizmo is moved to it, but never while it is held.
"""

from __future__ import annotations

import collections
import copy
import threading
import time

import mujoco
import numpy as np
import viser
from mjviser import ViserMujocoScene

from teleop.web.session_page.sim_thread import SimThread, Snapshot
from teleop.web.session_page.body_poses import BodyPoses
from teleop.web.shared.camera_markers import Markers, place_camera
from teleop.web.viser_internals.scene_stream import SceneStream

GIZMO_SCALE = 0.16  # m: big enough to grab, small enough not to hide the gripper
POSE_EPS = 1e-5
MOVE_EPS = 2e-5  # m (and quaternion entries): below this nothing visibly moved


def _quat_close(a: np.ndarray, b: np.ndarray) -> bool:
    return abs(abs(float(np.dot(a, b))) - 1.0) < 1e-8


class SceneDrawer:
    """Pushes the simulation's poses to every browser, up to `max_hz` updates a second, from viser's event loop."""

    def __init__(self, server: viser.ViserServer, sim: SimThread, gizmo=None, max_hz: float = 60.0) -> None:
        self.server = server
        self.sim = sim
        self.gizmo = gizmo
        self.period = 1.0 / max_hz
        self.update_s: collections.deque[float] = collections.deque(maxlen=600)
        self.updates = 0
        self.skipped = 0  # ticks with nothing visible moving: not sent
        self._sent: np.ndarray | None = None
        self.latency_ms: float | None = None
        self._last_input = 0.0
        self._last_tick = -1
        self.only_watched = False  # True: no updates while no browser is connected (a campaign's thrift)
        self._update_lock = threading.Lock()
        self._due = 0.0  # perf_counter s: the earliest the next update may go (max_hz)
        self._running = False
        self._cued = False  # a cue is queued on viser's loop and has not run yet
        snap = sim.snapshot
        self._generation = snap.generation
        self.model = copy.copy(snap.model)
        self.data = mujoco.MjData(self.model)
        place_camera(server)
        self.scene = ViserMujocoScene(server, self.model, num_envs=1)
        self.scene.camera_tracking_enabled = False  # keep world coordinates: gizmos and markers live there
        self.bodies = BodyPoses(self.scene)  # mjviser's update, a third of its cost
        self.markers = Markers(server, len(snap.targets))
        self.gizmos: list[viser.TransformControlsHandle] = []
        if gizmo is not None:
            for arm, (pos, quat) in enumerate(snap.targets):
                self.gizmos.append(self._add_gizmo(arm, pos, quat))
        self.stream = SceneStream(server)  # after the nodes it updates are made
        self.draw(snap)

    def _add_gizmo(self, arm: int, pos: np.ndarray, quat: np.ndarray) -> viser.TransformControlsHandle:
        handle = self.server.scene.add_transform_controls(
            f"/gizmo/arm{arm}", scale=GIZMO_SCALE, line_width=3.0, depth_test=False,
            position=tuple(pos), wxyz=tuple(quat),
        )
        gizmo = self.gizmo

        @handle.on_update
        async def _(event: viser.TransformControlsEvent) -> None:  # async: phases arrive in order
            gizmo.push(arm, event.target.position, event.target.wxyz, event.phase)

        return handle

    # -- life cycle ------------------------------------------------------
    def start(self) -> None:
        self._running = True
        self.sim.on_tick = self._cue

    def stop(self) -> None:
        self._running = False
        self.sim.on_tick = None

    def _cue(self) -> None:
        """In the control loop, after a tick: one call into viser's loop to draw it, unless one is queued or no
        page would see it (then nothing wakes)."""
        if self._cued or (self.only_watched and not self.stream.watched()):
            return
        self._cued = True  # before the call: the loop may run the draw, which clears it, before the call returns
        if not self.stream.soon(self._draw_latest):  # viser's loop has closed: the server is stopping
            self._cued = False

    def _draw_latest(self) -> None:
        """In viser's event loop: the newest snapshot, if it is new and the update's period is out."""
        self._cued = False
        snap = self.sim.snapshot
        if not self._running or (snap.tick == self._last_tick and snap.generation == self._generation):
            return
        now = time.perf_counter()
        if now < self._due:  # ticks come faster than max_hz: this one is not drawn, a later one is
            return
        self._due = self._due + self.period if now - self._due < self.period else now + self.period
        try:
            self.draw(snap)
        except Exception as exc:  # noqa: BLE001 - a drawing hiccup must not end the session
            print(f"drawing failed: {type(exc).__name__}: {exc}")

    # -- one update ------------------------------------------------------
    def draw(self, snap: Snapshot) -> float:
        """Send one scene update for `snap`; returns its server-side cost in seconds."""
        with self._update_lock:
            if snap.generation != self._generation:
                self._rebuild(snap)
            start = time.perf_counter()
            self._last_tick = snap.tick
            moved = self._moved(snap)
            # One block for the gizmos, the markers and the bodies: one message per scene node, all in one
            # frame written to each page when it ends (viser_internals.scene_stream.SceneStream), not a message per property
            # set for viser's sender to take in windows.
            with self.stream.update():
                self._sync_gizmos(snap)  # even when nothing moved: a drag may have ended on a clamped target
                if moved:
                    self._draw_markers(snap)
                    if self.bodies.entries is None:  # mjviser's own update: it reads an MjData
                        snap.pose(self.data)
                        self.bodies.update(self.data)
                    else:
                        self.bodies.update(snap)  # the tick's own body poses, no kinematics here
            if not moved:
                self.skipped += 1
                return 0.0
            cost = time.perf_counter() - start
            self.update_s.append(cost)
            self.updates += 1
            if snap.input_time > self._last_input:
                self._last_input = snap.input_time
                self.latency_ms = (time.monotonic() - snap.input_time) * 1000.0
            return cost

    def _moved(self, snap: Snapshot) -> bool:
        """Whether anything visible moved since the last update sent (a browser redraws on every update)."""
        poses = np.concatenate([snap.xpos.ravel(), snap.xquat.ravel(),
                                *(np.concatenate(t) for t in snap.targets), *(np.concatenate(e) for e in snap.ee)])
        if self._sent is not None and self._sent.shape == poses.shape and np.max(np.abs(poses - self._sent)) < MOVE_EPS:
            return False
        self._sent = poses
        return True

    def _draw_markers(self, snap: Snapshot) -> None:
        self.markers.draw(np.array([np.concatenate(t) for t in snap.targets]),
                          np.array([np.concatenate(e) for e in snap.ee]))

    def _sync_gizmos(self, snap: Snapshot) -> None:
        for arm, handle in enumerate(self.gizmos):
            if self.gizmo.busy(arm):
                continue
            pos, quat = snap.targets[arm]
            if np.max(np.abs(np.asarray(handle.position) - pos)) > POSE_EPS:
                handle.position = tuple(pos)
            if not _quat_close(np.asarray(handle.wxyz), quat):
                handle.wxyz = tuple(quat)

    def _rebuild(self, snap: Snapshot) -> None:
        """A reset compiled a new model (objects elsewhere, maybe fixed ones too): redraw its geometry."""
        self.model = copy.copy(snap.model)
        self.data = mujoco.MjData(self.model)
        self.scene.mj_model = self.model
        self.scene.mj_data = mujoco.MjData(self.model)
        self.scene.rebuild_visual_handles()
        self.bodies = BodyPoses(self.scene)
        self.stream.nodes_created()
        self._generation = snap.generation
        self._sent = None

    # -- figures ---------------------------------------------------------
    def update_ms(self) -> float:
        values = list(self.update_s)
        return float(np.median(values)) * 1000.0 if values else 0.0
