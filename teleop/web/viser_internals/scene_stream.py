"""A page's scene updates written by us, not by viser's sender (`SceneStream`), and a node's property sets
collected into them (`set_arrays`, `send_updates`, and three process-wide patches: `collect_scene_updates`,
applied by teleop.web.viser_internals.install).

viser queues every property set as a message in its broadcast buffer; its sender task then
wakes, takes a window, serializes it per page and awaits the send: about 1.3 ms of CPU an
update in a loaded session, for 13 messages. `SceneStream.update()` is a block in which a
scene handle's property sets (`SceneNodeHandle._queue_update`) and its owner-stamped
messages such as a position or orientation (`SceneApi._queue_scene_message`, which stamps
`owner`) are collected in the thread, one message per node, and `ViserServer.flush` does
nothing (mjviser flushes inside its own update). At its end the messages become one frame of
viser's wire format (its `_message_producer`: the msgpack's size, the zstd'd size, zstd'd
msgpack of `{"messages", "timestampSec", "binaryBufferLengths"}`, then the arrays 8-byte
aligned by `_append_aligned_buffers`, each a `{"__binary_index", "dtype"}` placeholder in its
message), written in viser's event loop (`_broadcast_buffer.event_loop`) to each of the
server's connections (`_websock_server._live_connections`) with websockets'
`protocol.send_binary` and `send_data()`. A page gets frames only once viser's sender has
taken everything up to the nodes' creation (`_broadcast_buffer.generator_cursors`, against
`message_counter`): a frame never overtakes the node it updates. A page that missed one (not
caught up yet, or its socket holding over a megabyte) gets the whole newest state next, as
viser's buffer would have replayed it.

- `set_arrays`: what viser's setter does for a float-array property (cast to the
  stored array's dtype, nothing sent when equal, the stored array updated in place, a
  private copy queued: `AssignablePropsBase`'s `props_setattr`), for several of one
  node's properties at once and without its per-call type checks: one message.
- `send_updates`: a node's updates, already stored in its properties, into the open block,
  or to viser as one message (teleop.web.session_page.body_poses sets mjviser's body handles
  through it, with teleop.web.viser_internals.mjviser_poses).

Why viser needs these and what upstream change would retire them: the package's docstring
(teleop/web/viser_internals/__init__.py).
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import msgspec.msgpack
import numpy as np
import viser
import zstandard
from viser._messages import SceneNodeUpdateMessage
from viser._scene_api import SceneApi
from viser._scene_handles import SceneNodeHandle
from viser.infra._infra import _append_aligned_buffers
from websockets.protocol import OPEN

_PATCH_LOCK = threading.Lock()
_PENDING = threading.local()  # while a SceneStream.update block is open in the thread: .updates
# {(id(scene api), node name): (scene api, name, {prop: value})} and .messages [owner-stamped scene messages]


def _coalesce_scene_updates() -> None:
    """Make SceneNodeHandle._queue_update collect into an open SceneStream.update block of its thread, one
    message per node (once per process)."""
    with _PATCH_LOCK:
        original = SceneNodeHandle._queue_update  # noqa: SLF001
        if getattr(original, "coalescing", False):
            return

        def queue_update(self, name, value):
            if not _pend(self._impl, {name: value}):  # noqa: SLF001
                return original(self, name, value)

        queue_update.coalescing = True  # type: ignore[attr-defined]
        queue_update.original = original  # type: ignore[attr-defined]
        SceneNodeHandle._queue_update = queue_update  # noqa: SLF001


def _pend(impl, updates: dict) -> bool:
    """Add a node's property updates to this thread's open SceneStream.update block; False if none is open."""
    pending = getattr(_PENDING, "updates", None)
    if pending is None:
        return False
    entry = pending.get((id(impl.api), impl.name))
    if entry is None:
        pending[(id(impl.api), impl.name)] = (impl.api, impl.name, updates)
    else:
        entry[2].update(updates)
    return True


def _quiet_flush_in_updates() -> None:
    """Make ViserServer.flush do nothing inside a SceneStream.update block of its thread (once per process)."""
    with _PATCH_LOCK:
        original = viser.ViserServer.flush
        if getattr(original, "quiet_in_updates", False):
            return

        def flush(self) -> None:
            if getattr(_PENDING, "updates", None) is None:
                original(self)

        flush.quiet_in_updates = True  # type: ignore[attr-defined]
        flush.original = original  # type: ignore[attr-defined]
        viser.ViserServer.flush = flush


def set_arrays(handle, **arrays: np.ndarray) -> None:
    """Give a scene node float-array properties as viser's setter does, in one message (see above)."""
    impl = handle._impl  # noqa: SLF001
    if impl.removed:
        return
    props = impl.props
    updates = {}
    for name, value in arrays.items():
        current = getattr(props, name)
        value = np.array(value, dtype=current.dtype)  # a copy: the stored array and the queued one never alias it
        if value.shape == current.shape:
            if np.array_equal(current, value):
                continue
            current[...] = value
        else:
            setattr(props, name, value.copy())
        updates[name] = value
    if updates:
        _send_updates(impl, updates)


def send_updates(handle, updates: dict) -> None:
    """A scene node's property updates {name: value}, already stored in its properties (as
    teleop.web.viser_internals.mjviser_poses.stored_poses hands them out): into this thread's open
    SceneStream.update block, else to viser as one message. Nothing for a node already removed."""
    impl = handle._impl  # noqa: SLF001
    if not impl.removed:
        _send_updates(impl, updates)


def _send_updates(impl, updates: dict) -> None:
    if not _pend(impl, updates):
        impl.api._queue_scene_message(SceneNodeUpdateMessage(impl.name, updates))  # noqa: SLF001 - it stamps the owner


class SceneStream:
    """One server's scene updates written straight to its pages' websockets (see the module's docstring).

    `update()` is a block; what it sets goes out as one frame in viser's wire format, written to
    every page from viser's event loop in one callback (at once when the block runs in that loop, as
    the drawer's does): no message buffer, no window, no sender task. A page gets frames once viser's
    sender has written it everything up to `nodes_created()` (the nodes the frames update); a page that
    missed a frame (not yet caught up, or its socket backed up) gets the whole state next.
    """

    WRITE_LIMIT = 1 << 20  # bytes: a page whose socket holds more than this is skipped until it drains

    def __init__(self, server: viser.ViserServer) -> None:
        if not scene_updates_collected():
            raise RuntimeError("SceneStream needs viser's scene updates collected: call "
                               "teleop.web.viser_internals.install() when the app starts")
        self._server = server._websock_server  # noqa: SLF001
        self._buffer = self._server._broadcast_buffer  # noqa: SLF001
        self._loop = self._buffer.event_loop
        self._latest: dict = {}  # caller's thread: the newest message of each redundancy key (viser's), oldest first
        self._fresh: set[int] = set()  # event loop: pages that have had every frame since a whole state
        self._generation = 0
        self._sent_generation = 0
        self._compress = zstandard.ZstdCompressor(level=1)  # caller's thread (a compressor is one thread's)
        self._compress_loop = zstandard.ZstdCompressor(level=1)  # the event loop's
        self.frames = 0
        self.nodes_created()

    def nodes_created(self) -> None:
        """Call after adding or re-creating the nodes updated: pages get frames once viser sent them all that."""
        with self._buffer.buffer_lock:
            self._barrier = self._buffer.message_counter - 1
        self._latest = {}
        self._generation += 1

    @contextmanager
    def update(self) -> Iterator[None]:
        if getattr(_PENDING, "updates", None) is not None:
            raise RuntimeError("SceneStream.update() inside another scene block")
        _PENDING.updates = pending = {}
        _PENDING.messages = messages = []
        try:
            yield
        finally:
            _PENDING.updates = None
            _PENDING.messages = None
        messages += [SceneNodeUpdateMessage(name, updates, owner=api._owner_id)  # noqa: SLF001
                     for api, name, updates in pending.values()]
        if messages:
            self._send(messages)
        else:
            self._catch_up()

    def soon(self, callback: Callable[[], None]) -> bool:
        """Run `callback` in viser's event loop (from any thread); False if that loop has closed."""
        try:
            self._loop.call_soon_threadsafe(callback)
        except RuntimeError:
            return False
        return True

    def watched(self) -> bool:
        """Whether a page is connected (any thread)."""
        return bool(self._server._live_connections)  # noqa: SLF001

    def _send(self, messages: list) -> None:
        latest = self._latest
        for message in messages:
            key = message.redundancy_key()
            latest.pop(key, None)  # re-inserted last: the whole state replays in the order things last changed
            latest[key] = message
        if self._server._live_connections:  # noqa: SLF001 - no page: the newest state is kept for the next
            self._hand_over(wire_frame(messages, self._compress), tuple(latest.values()))

    def _catch_up(self) -> None:
        """Nothing changed: a page that has not had the whole state (one that just opened) gets it now."""
        live = self._server._live_connections  # noqa: SLF001
        if self._latest and not all(client in self._fresh for client in list(live)):
            self._hand_over(None, tuple(self._latest.values()))

    def _hand_over(self, frame: bytes | None, state: tuple) -> None:
        barrier, generation = self._barrier, self._generation
        if _running_loop() is self._loop:  # already in viser's loop: written now
            self._write(frame, state, barrier, generation)
        else:
            self.soon(lambda: self._write(frame, state, barrier, generation))

    def _write(self, frame: bytes | None, state: tuple, barrier: int, generation: int) -> None:
        """In viser's event loop: the frame to each page that is caught up, the whole state to one that is new
        (only that with no frame)."""
        live = self._server._live_connections  # noqa: SLF001
        if generation != self._sent_generation:
            self._fresh.clear()
            self._sent_generation = generation
        self._fresh.intersection_update(live)
        whole = None
        for client, connection in list(live.items()):
            transport = connection.transport
            if (self._buffer.generator_cursors.get(client, -1) < barrier or connection.protocol.state is not OPEN
                    or connection.send_in_progress is not None or transport.get_write_buffer_size() > self.WRITE_LIMIT):
                self._fresh.discard(client)
                continue
            if client in self._fresh:
                if frame is None:
                    continue
                data = frame
            else:
                data = whole = whole or wire_frame(state, self._compress_loop)
            connection.protocol.send_binary(data)
            connection.send_data()
            self._fresh.add(client)
            self.frames += 1


def _collect_scene_messages() -> None:
    """Make SceneApi._queue_scene_message (owner-stamped scene messages, such as a node's position and orientation
    sets) collect into an open SceneStream.update block of its thread (once per process)."""
    with _PATCH_LOCK:
        original = SceneApi._queue_scene_message  # noqa: SLF001
        if getattr(original, "collecting", False):
            return

        def queue_scene_message(self, message) -> None:
            collected = getattr(_PENDING, "messages", None)
            if collected is None:
                return original(self, message)
            message.owner = self._owner_id  # noqa: SLF001 - as viser stamps it
            collected.append(message)

        queue_scene_message.collecting = True  # type: ignore[attr-defined]
        queue_scene_message.original = original  # type: ignore[attr-defined]
        SceneApi._queue_scene_message = queue_scene_message  # noqa: SLF001


def collect_scene_updates() -> None:
    """The process-wide patches SceneStream.update blocks rely on (idempotent): a node's property sets and
    owner-stamped scene messages collected into the thread's open block, viser's flush quiet inside it."""
    _coalesce_scene_updates()
    _quiet_flush_in_updates()
    _collect_scene_messages()


def scene_updates_collected() -> bool:
    """Whether collect_scene_updates is in place."""
    return (getattr(SceneNodeHandle._queue_update, "coalescing", False)  # noqa: SLF001
            and getattr(viser.ViserServer.flush, "quiet_in_updates", False)
            and getattr(SceneApi._queue_scene_message, "collecting", False))  # noqa: SLF001


def serializable(message, binary: list[memoryview]) -> dict:
    """viser's `as_serializable_dict(binary)`, quicker for what a scene update mostly is: a node's properties
    that are all C-contiguous arrays (each goes out as a binary buffer with viser's placeholder)."""
    if type(message) is SceneNodeUpdateMessage:
        values = message.updates.values()
        if all(type(v) is np.ndarray and v.flags.c_contiguous for v in values):
            updates = {}
            for name, value in message.updates.items():
                updates[name] = {"__binary_index": len(binary), "dtype": value.dtype.str}
                binary.append(value.data)
            return {"name": message.name, "updates": updates, "owner": message.owner, "type": "SceneNodeUpdateMessage"}
    return message.as_serializable_dict(binary)


def _running_loop() -> asyncio.AbstractEventLoop | None:
    try:
        return asyncio.get_running_loop()
    except RuntimeError:
        return None


def wire_frame(messages, compress) -> bytes:
    """Messages as one websocket frame of viser's wire format (its `_message_producer`: zstd'd msgpack, then the
    arrays 8-byte aligned)."""
    binary: list[memoryview] = []
    serialized = tuple(serializable(message, binary) for message in messages)
    inner = msgspec.msgpack.encode({"messages": serialized, "timestampSec": time.perf_counter(),
                                    "binaryBufferLengths": tuple(b.nbytes for b in binary)})
    compressed = compress.compress(inner)
    parts: list = [len(inner).to_bytes(8, "little"), len(compressed).to_bytes(8, "little"), compressed]
    _append_aligned_buffers(parts, binary, 16 + len(compressed))
    return b"".join(parts)
