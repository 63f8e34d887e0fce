"""The page's own websocket to the server (`/teleop/input`), beside viser's on the same port, and the
script every 3D page runs to speak on it (`channel_script`: page_input.js with its settings).

viser 1.1 does not forward browser keys to Python, so the page runs a small
script (page_input.js) that sends them here; the replay viewer's page runs it with no keys bound, for its
renderer report and its lost-server banner. The channel is the only way in
for those messages, and it bounds what a page can make the server do: each
connection may send messages of at most `input_messages.MAX_BYTES` (frames over
MAX_FRAME close it), at most RATE per second (with a burst of BURST), and
there are at most MAX_CONNECTIONS at once. Every message is validated
(`input_messages.parse`); one that fails, or comes too fast, is dropped and
counted, and the connection carries on. The token rule and an Origin check
are applied before the handshake (teleop.web.viser_internals.guarded_start, by teleop.web.shared.access's rules).

Handlers run on viser's event loop thread; the listener's methods are called
there, one message at a time, and must only update thread-safe state (the
key state the control loop polls), so nothing a page sends can raise in the
control loop. Every PING_S the channel pings each page at the websocket level;
when the pong does not come back within QUIET_S (a network that stalled without
closing, a laptop gone to sleep) the listener hears `quiet`, so held keys are let
go. The browser's network stack answers pings by itself, so a page that is
only slow to run its script (software WebGL hogging its main thread) is not
taken for gone; its key releases arrive late, as any of its input does.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import time
import traceback
from pathlib import Path
from typing import Protocol

from websockets.asyncio.server import ServerConnection
from websockets.exceptions import ConnectionClosed

from teleop.web.shared.input_messages import PATH, InputMessage, Rejected, parse
from teleop.web.viser_internals.serving_hooks import limit_message_size

MAX_FRAME = 64 * 1024  # bigger frames close the connection (websockets' limit; code 1009)
RATE = 300.0  # messages per second, sustained, per connection: keys, a pad at 60 Hz and a SpaceMouse at 125 Hz
BURST = 600.0
MAX_CONNECTIONS = 32
PING_S = 0.25  # websocket pings to each page this often...
QUIET_S = 1.0  # ...and a pong later than this releases its keys
SCRIPT = Path(__file__).with_name("page_input.js")


def channel_script(client: int, keys: list[str]) -> str:
    """page_input.js for viser's client `client`, catching `keys` (none: the channel only, for other devices)."""
    config = {"path": PATH, "keys": list(keys), "client": int(client)}
    return f"const CONFIG = {json.dumps(config)};\n" + SCRIPT.read_text(encoding="utf-8")


class InputListener(Protocol):
    """What the channel tells about connections and their valid messages (called on the network thread)."""

    def opened(self, conn: int, remote: str) -> None: ...

    def received(self, conn: int, message: InputMessage) -> None: ...

    def quiet(self, conn: int) -> None: ...

    def closed(self, conn: int) -> None: ...


class TokenBucket:
    """Per connection: `take()` is False when it sends faster than `rate` messages a second (beyond `burst`)."""

    def __init__(self, rate: float = RATE, burst: float = BURST) -> None:
        self.rate, self.burst = rate, burst
        self.level, self.stamp = burst, time.monotonic()

    def take(self) -> bool:
        now = time.monotonic()
        self.level = min(self.burst, self.level + (now - self.stamp) * self.rate)
        self.stamp = now
        if self.level < 1.0:
            return False
        self.level -= 1.0
        return True


class ChannelCounts:
    """What a page's websocket channel counts and reports (the input channel's and the XR page's alike)."""

    def __init__(self) -> None:
        self.accepted = 0  # valid messages handed on
        self.dropped = 0  # malformed, out of range, too fast or too big
        self.last_drop = ""  # why the newest dropped message was dropped (one line)
        self.connections = 0

    def drop(self, reason: str) -> None:
        self.dropped += 1
        self.last_drop = reason

    def status(self) -> dict:
        return {"connections": self.connections, "accepted": self.accepted, "dropped": self.dropped,
                "last_drop": self.last_drop or None}


class InputChannel(ChannelCounts):
    """Accepts page connections on PATH, validates, rate-limits and counts their messages."""

    def __init__(self, listener: InputListener | None = None) -> None:
        super().__init__()
        self.listener = listener
        self.listener_errors = 0
        self._ids = itertools.count(1)

    def _tell(self, method: str, *args) -> None:
        """Call the listener; its bug is counted and printed, never passed on to the page or the loop."""
        if self.listener is None:
            return
        try:
            getattr(self.listener, method)(*args)
        except Exception:  # noqa: BLE001 - a listener bug must not close the channel
            self.listener_errors += 1
            if self.listener_errors <= 3:
                traceback.print_exc()

    async def handle(self, connection: ServerConnection) -> None:
        """One page's connection, until it closes (the websocket route for PATH)."""
        if self.connections >= MAX_CONNECTIONS:
            self.drop("too many input connections")
            await connection.close(1013, "too many input connections")
            return
        self.connections += 1
        conn = next(self._ids)
        limit_message_size(connection, MAX_FRAME)  # viser lets its own socket take 50 MB; a page's keys need 512 B
        remote = connection.remote_address[0] if connection.remote_address else "?"
        bucket = TokenBucket()
        self._tell("opened", conn, str(remote))
        watch = asyncio.create_task(self._watch(connection, conn))
        try:
            async for raw in connection:
                if not bucket.take():
                    self.drop("more than {:g} messages a second".format(RATE))
                    continue
                try:
                    message = parse(raw)
                except Rejected as exc:
                    self.drop(str(exc))
                    continue
                self.accepted += 1
                self._tell("received", conn, message)
        except ConnectionClosed as exc:
            if exc.sent is not None and exc.sent.code == 1009:
                self.drop(f"frame over {MAX_FRAME} bytes (connection closed)")
        finally:
            watch.cancel()
            self.connections -= 1
            self._tell("closed", conn)

    async def _watch(self, connection: ServerConnection, conn: int) -> None:
        """Ping the page every PING_S; a pong later than QUIET_S means `quiet` (its keys are let go)."""
        late = False
        while True:
            await asyncio.sleep(PING_S)
            try:
                pong = await connection.ping()
                await asyncio.wait_for(pong, QUIET_S)
                late = False
            except TimeoutError:
                if not late:  # once per silence
                    self._tell("quiet", conn)
                late = True
            except ConnectionClosed:
                return
