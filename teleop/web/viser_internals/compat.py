"""Everything teleop relies on in viser, mjviser and websockets beyond their public APIs, in one place.

viser (pinned to 1.1.x in pyproject.toml) has no public call for some things the
served page needs, so teleop uses a few of its internals. Only this module touches
them (tests/test_architecture.py checks that), and tests/test_viser_contract.py
checks each one against the installed viser, naming what changed when a release
breaks one:

- `run_javascript`: viser's client runs the source of a `RunJavascriptMessage`
  (`viser._messages`) with `Function(source)()` (viser's `add_plotly` uses it);
  it is queued on one client's connection (`ClientHandle._websock_connection`).
- `wrapping_serve`: `ViserServer()` starts its one HTTP + websocket server with
  `websockets.asyncio.server.serve(handler, host, port, ..., process_request=...)`,
  looked up at call time; while the context is open that function lets us change
  the handler and `process_request` (the token gate and the input channel's route,
  teleop.web.shared.access), so viser's own serving code runs unchanged behind them.
- `INDEX_PATHS`, `with_head_script`: viser answers its page (its
  `client/build/index.html`, one `<head>`) at `/`, gzipped when the browser accepts
  gzip; a script of ours goes first in that `<head>` (teleop.web.session_page.view_quality).
- `FIXED_DPR_PARAM`: the URL query parameter viser's client reads when it starts,
  the canvas' device pixels per CSS pixel.
- `GUI_BUTTON_SELECTOR`: a GUI button from `gui.add_button(label)` is a `<button>`
  element whose text is its label; page scripts (page_devices.js) find the panel's
  buttons by selector and label, both handed to them from Python.
- `limit_message_size`: websockets' per-connection limit on incoming messages
  (viser sets 50 MB on every connection of its server, ours included).
- `quick_array_casts`: every property a handle is given goes through
  `AssignablePropsBase._cast_value_recursive`, which compares the property's type hint
  with `npt.NDArray[np.float16]`, `[np.float32]` and `[np.float64]` built anew at each
  call (typing's substitution machinery: ~20-35 us a property, a third of a scene
  update's cost). For a float-array hint it now looks the dtype up in a table built
  once, and casts as viser does (`np.asarray(value).astype(dtype)`); any other hint
  goes to viser's own function unchanged.
- `SceneStream`: a page's scene updates written by us, not by viser's sender. viser
  queues every property set as a message in its broadcast buffer; its sender task then
  wakes, takes a window, serializes it per page and awaits the send: about 1.3 ms of CPU
  an update in a loaded session, for 13 messages. `SceneStream.update()` is a block in
  which a scene handle's property sets (`SceneNodeHandle._queue_update`) and its
  owner-stamped messages such as a position or orientation
  (`SceneApi._queue_scene_message`, which stamps `owner`) are collected in the thread,
  one message per node, and `ViserServer.flush` does nothing (mjviser flushes inside its
  own update). At its end the messages become one frame of viser's wire format (its
  `_message_producer`: the msgpack's size, the zstd'd size, zstd'd msgpack of
  `{"messages", "timestampSec", "binaryBufferLengths"}`, then the arrays 8-byte aligned
  by `_append_aligned_buffers`, each a `{"__binary_index", "dtype"}` placeholder in its
  message), written in viser's event loop (`_broadcast_buffer.event_loop`) to each of
  the server's connections (`_websock_server._live_connections`) with websockets'
  `protocol.send_binary` and `send_data()`. A page gets frames only once viser's sender
  has taken everything up to the nodes' creation (`_broadcast_buffer.generator_cursors`,
  against `message_counter`): a frame never overtakes the node it updates. A page
  that missed one (not caught up yet, or its socket holding over a megabyte) gets the
  whole newest state next, as viser's buffer would have replayed it.
- `set_arrays`: what viser's setter does for a float-array property (cast to the
  stored array's dtype, nothing sent when equal, the stored array updated in place, a
  private copy queued: `AssignablePropsBase`'s `props_setattr`), for several of one
  node's properties at once and without its per-call type checks: one message.
- `send_updates`: a node's updates into the open block, or to viser as one message
  (`teleop.web.session_page.body_poses.BodyPoses` sets mjviser's body handles through it).
"""

from __future__ import annotations

import asyncio
import gzip
import threading
import time
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager

import msgspec.msgpack
import numpy as np
import numpy.typing as npt
import viser
import websockets.asyncio.server
import zstandard
from viser._assignable_props_api import AssignablePropsBase
from viser._messages import RunJavascriptMessage, SceneNodeUpdateMessage
from viser._scene_handles import SceneNodeHandle
from viser.infra._infra import _append_aligned_buffers
from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response
from websockets.protocol import OPEN

Handler = Callable[[ServerConnection], Awaitable[None]]
ProcessRequest = Callable[[ServerConnection, Request], "Response | None | Awaitable[Response | None]"]
ServeWrap = Callable[[Handler, "ProcessRequest | None"], "tuple[Handler, ProcessRequest | None]"]

INDEX_PATHS = ("/", "/index.html")  # where viser answers its page
FIXED_DPR_PARAM = "fixedDpr"  # ?fixedDpr=0.5: viser's client draws its canvas at 0.5 device pixels per CSS pixel
GUI_BUTTON_SELECTOR = "button"  # the element a viser GUI button is drawn as; its text is the button's label
WEBSOCKET_PROTOCOL = f"viser-v{viser.__version__}"  # the subprotocol a client of viser's websocket must ask for


def viewer_camera_message() -> bytes:
    """The message a page sends when its 3D view opens (msgpack, viser's ViewerCameraMessage). viser counts a
    client as connected, and sends it scene updates, from its first one: a client of the websocket that is not a
    browser (the campaign bench's watching pages) sends it to be watched like one."""
    import msgspec.msgpack  # viser's own wire format

    return msgspec.msgpack.encode({
        "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [1.5, 0.0, 1.0], "fov": 0.9,
        "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 800, "look_at": [0.0, 0.0, 0.0],
        "up_direction": [0.0, 0.0, 1.0]})


def run_javascript(client: viser.ClientHandle, source: str) -> None:
    """Run `source` in one browser's page (viser's client: `Function(source)()`), after what is queued before."""
    client._websock_connection.queue_message(RunJavascriptMessage(source=source))  # noqa: SLF001


_SERVE_LOCK = threading.Lock()  # one wrapped start at a time: the replacement is process-wide while it lasts


@contextmanager
def wrapping_serve(wrap: ServeWrap) -> Iterator[list[bool]]:
    """While open, a server viser starts gets `wrap(handler, process_request)` in place of its own two;
    yields a list that gains an entry per server so started (empty: viser did not start through the call)."""
    module = websockets.asyncio.server
    original = module.serve
    wrapped: list[bool] = []

    def serve(handler: Handler, *args, process_request: ProcessRequest | None = None, **kwargs):
        wrapped.append(True)
        handler, process_request = wrap(handler, process_request)
        return original(handler, *args, process_request=process_request, **kwargs)

    with _SERVE_LOCK:
        module.serve = serve
        try:
            yield wrapped
        finally:
            module.serve = original


def with_head_script(response: Response, script: bytes, cache: dict) -> Response:
    """viser's page with `script` first in its <head> (before viser's own code runs), same encoding.

    `cache` maps a page body as viser sent it to the edited one (viser sends the
    same bytes each time, so the page is edited once per encoding).
    """
    if "text/html" not in response.headers.get("Content-Type", ""):
        return response
    key = bytes(response.body)
    if key not in cache:
        zipped = response.headers.get("Content-Encoding", "") == "gzip"
        html = gzip.decompress(key) if zipped else key
        head = html.find(b"<head>")
        if head < 0:
            cache[key] = key
        else:
            html = html[: head + 6] + script + html[head + 6:]
            cache[key] = gzip.compress(html) if zipped else html
    body = cache[key]
    headers = Headers([(k, v) for k, v in response.headers.raw_items() if k.lower() != "content-length"])
    headers["Content-Length"] = str(len(body))  # websockets' Headers add a value on assignment
    return Response(response.status_code, response.reason_phrase, headers, body)


def limit_message_size(connection: ServerConnection, max_bytes: int) -> None:
    """Close `connection` (code 1009) on an incoming message over `max_bytes`, not viser's 50 MB."""
    protocol = getattr(connection, "protocol", None)
    if protocol is not None and hasattr(protocol, "max_message_size"):
        protocol.max_message_size = max_bytes


FLOAT_ARRAY_HINTS = {npt.NDArray[t]: t for t in (np.float16, np.float32, np.float64)}  # viser's float-array hints
_CAST_LOCK = threading.Lock()


def quick_array_casts() -> None:
    """Make viser's property cast look float-array hints up in FLOAT_ARRAY_HINTS (once per process; see above)."""
    with _CAST_LOCK:
        original = AssignablePropsBase._cast_value_recursive  # noqa: SLF001
        if getattr(original, "quick", False):
            return

        def cast(self, hint, value, prop_name):
            try:
                dtype = FLOAT_ARRAY_HINTS.get(hint)
            except TypeError:  # an unhashable hint: viser's own comparisons
                dtype = None
            if dtype is not None:
                return np.asarray(value).astype(dtype)
            return original(self, hint, value, prop_name)

        cast.quick = True  # type: ignore[attr-defined]
        cast.original = original  # type: ignore[attr-defined]
        AssignablePropsBase._cast_value_recursive = cast  # noqa: SLF001


_PENDING = threading.local()  # while a SceneStream.update block is open in the thread: .updates
# {(id(scene api), node name): (scene api, name, {prop: value})} and .messages [owner-stamped scene messages]


def _coalesce_scene_updates() -> None:
    """Make SceneNodeHandle._queue_update collect into an open SceneStream.update block of its thread, one
    message per node (once per process)."""
    with _CAST_LOCK:
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
    with _CAST_LOCK:
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
        send_updates(impl, updates)


def send_updates(impl, updates: dict) -> None:
    """A node's (`handle._impl`) property updates, already stored in its props: into this thread's open
    SceneStream.update block, else to viser as one message (its scene API stamps the owner)."""
    if not _pend(impl, updates):
        impl.api._queue_scene_message(SceneNodeUpdateMessage(impl.name, updates))  # noqa: SLF001


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
        _coalesce_scene_updates()
        _quiet_flush_in_updates()
        _collect_scene_messages()
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
    from viser._scene_api import SceneApi

    with _CAST_LOCK:
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
