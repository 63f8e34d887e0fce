"""The XR page's websocket (`/teleop/xr`), beside viser's and the input channel on the session's port.

To the page: the scene message once (and again when a reset builds a new model), then every control
tick the poses message (teleop/web/xr_page/scene_message.py), and the panel's state as JSON text a
few times a second. From the page: its controllers' and hands' poses and buttons
(teleop/web/xr_page/xr_messages.py), checked, rate-limited and counted like the input channel's, and
handed to the `xr` device. A page that closes, or whose pongs stop for QUIET_S, lets go of every
clutch it held. The token gate and the Origin check run before the handshake (teleop.web.shared.access).

`tick()` is called on the control loop's thread after every tick; it only stores the newest frame
and wakes the connections' senders on the server's event loop.
"""

from __future__ import annotations

import asyncio
import json
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from teleop.web.shared.input_channel import ChannelCounts, TokenBucket
from teleop.web.viser_internals.serving_hooks import limit_message_size
from teleop.web.xr_page.scene_message import poses_message
from teleop.web.xr_page.xr_device import XrDevice
from teleop.web.xr_page.xr_messages import XrButton, XrConfig, XrPose, XrRelease, Rejected, parse

PATH = "/teleop/xr"
MAX_FRAME = 4096
RATE = 400.0  # messages a second per connection: two hands at a headset's 90 Hz, with room
MAX_CONNECTIONS = 8
PING_S, QUIET_S = 0.25, 1.0
STATUS_PERIOD_S = 0.25


@dataclass(frozen=True)
class XrFrame:
    """What one control tick leaves for the pages: the bodies' world poses and each arm's finger force (N)."""

    tick: int
    generation: int  # changes when a reset builds a new model (the scene is sent again)
    sim_time: float
    xpos: np.ndarray
    xquat: np.ndarray
    forces: np.ndarray
    errors: np.ndarray  # each arm's IK tracking error (m)


class XrChannel(ChannelCounts):
    """Serves XR pages: scene, poses and status out; poses and buttons in, to `device`."""

    def __init__(self, device: XrDevice, scene: Callable[[int], bytes], status: Callable[[], dict] | None = None) -> None:
        self.device = device
        self.scene = scene  # generation -> the scene message of that model
        self.status_source = status
        super().__init__()
        self.poses_sent = 0
        self._frame: XrFrame | None = None
        self._waiters: set[asyncio.Event] = set()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._lock = threading.Lock()

    def status(self) -> dict:
        return {**super().status(), "poses_sent": self.poses_sent, **self.device.status_counts()}

    # -- the control loop's side ------------------------------------------------
    def tick(self, frame: XrFrame) -> None:
        """The newest tick (control loop thread): stored, and the pages' senders woken."""
        with self._lock:
            self._frame = frame
            loop, waiters = self._loop, list(self._waiters)
        if loop is not None and waiters:
            try:
                loop.call_soon_threadsafe(lambda: [w.set() for w in waiters])
            except RuntimeError:  # the server's loop closed
                pass

    # -- the server's event loop -------------------------------------------------
    def _message(self, message) -> None:
        if isinstance(message, XrPose):
            self.device.push_pose(message.hand, message.frame, message.tracked, message.pos, message.quat, message.clutch,
                                  message.opening, message.mode, message.t_ms)
        elif isinstance(message, XrButton):
            self.device.press(message.hand, message.button)
        elif isinstance(message, XrRelease):
            self.device.release(message.why)
        elif isinstance(message, XrConfig):
            self.device.scale = message.scale

    async def handle(self, connection: ServerConnection) -> None:
        """One XR page's connection, until it closes (the websocket route for PATH)."""
        if self.connections >= MAX_CONNECTIONS:
            self.drop("too many XR connections")
            await connection.close(1013, "too many XR connections")
            return
        self.connections += 1
        limit_message_size(connection, MAX_FRAME)
        wake = asyncio.Event()
        with self._lock:
            self._loop = asyncio.get_running_loop()
            self._waiters.add(wake)
        sender = asyncio.create_task(self._send(connection, wake))
        watch = asyncio.create_task(self._watch(connection))
        bucket = TokenBucket(RATE, burst=RATE)
        try:
            async for raw in connection:
                if not bucket.take():
                    self.drop(f"more than {RATE:g} messages a second")
                    continue
                try:
                    message = parse(raw)
                except Rejected as exc:
                    self.drop(str(exc))
                    continue
                self.accepted += 1
                self._message(message)
        except ConnectionClosed:
            pass
        finally:
            sender.cancel()
            watch.cancel()
            with self._lock:
                self._waiters.discard(wake)
            self.connections -= 1
            self.device.release("page closed")

    async def _send(self, connection: ServerConnection, wake: asyncio.Event) -> None:
        generation, last_tick, status_due, last_status = None, -1, 0.0, None
        try:
            while True:
                await wake.wait()
                wake.clear()
                frame = self._frame
                if frame is None or frame.tick == last_tick:
                    continue
                if frame.generation != generation:
                    generation = frame.generation
                    await connection.send(await asyncio.to_thread(self.scene, generation))
                last_tick = frame.tick
                await connection.send(poses_message(frame.tick, frame.sim_time, frame.xpos, frame.xquat,
                                                    self.device.applied_frame, frame.forces, frame.errors))
                self.poses_sent += 1
                now = time.monotonic()
                if self.status_source is not None and now >= status_due:
                    status_due = now + STATUS_PERIOD_S
                    status = self.status_source()
                    if status != last_status:
                        last_status = status
                        await connection.send(json.dumps({"type": "status", **status}))
        except ConnectionClosed:
            return

    async def _watch(self, connection: ServerConnection) -> None:
        """A page whose pongs stop for QUIET_S (a headset taken off, Wi-Fi gone) lets go of its clutches."""
        while True:
            await asyncio.sleep(PING_S)
            try:
                pong = await connection.ping()
                await asyncio.wait_for(pong, QUIET_S)
            except TimeoutError:
                self.device.release("page quiet")
            except ConnectionClosed:
                return
