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
  teleop.web.access), so viser's own serving code runs unchanged behind them.
- `INDEX_PATHS`, `with_head_script`: viser answers its page (its
  `client/build/index.html`, one `<head>`) at `/`, gzipped when the browser accepts
  gzip; a script of ours goes first in that `<head>` (teleop.web.view_quality).
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
- `one_message_per_node` (for what still goes through viser's setters, such as
  mjviser's own update where `BodyPoses` falls back to it): a scene handle queues each
  property it is given as its own
  `SceneNodeUpdateMessage(name, {prop: value})` (`SceneNodeHandle._queue_update`),
  though the message carries a dict of updates and the client applies them all. A
  scene update gives most bodies a position and an orientation: within the block
  (its thread only) each node's properties go out as one message, which halves the
  messages viser's buffer indexes and its sender serializes (21 to 13 an update on
  lift). viser's redundancy key for such a message is the node and its sorted property
  names, so a newer update still replaces an unsent one.
- `scene_update`: one scene update, one wake-up of viser's sender. A block of
  `ViserServer.atomic()` wakes the sender's event loop (`call_soon_threadsafe`) when it
  ends, a `flush()` once more, and mjviser flushes inside its own block besides, where
  the sender can take nothing yet; a property set before the block is a message and a
  wake of its own. `scene_update` is an atomic block on the broadcast buffer
  (`_websock_server._broadcast_buffer`: `atomic_start`, `atomic_counter` under
  `buffer_lock`, `message_event`, `flush_event`, `event_loop`) with
  `one_message_per_node` inside; `ViserServer.flush` does nothing in its thread while
  it is open, and at its end one callback sets both events, only if a message was queued.
- `set_arrays`: what viser's setter does for a float-array property (cast to the
  stored array's dtype, nothing sent when equal, the stored array updated in place, a
  private copy queued: `AssignablePropsBase`'s `props_setattr`), for several of one
  node's properties at once and without its per-call type checks: one message.
- `BodyPoses`: mjviser's `update_from_mjdata` for our pages (one environment, no camera
  tracking, no overlay, no convex hulls), from mjviser's handles (`_mesh_groups`: each
  `handle`, `body_ids`, `mocap_ids`; `site_handles_by_group`) and MuJoCo's own body
  quaternions (`xquat`, which mjviser recomputes from `xmat` each update). It costs
  about a third of mjviser's update; where mjviser is not as described (another
  release, an overlay switched on), it calls mjviser's update.
"""

from __future__ import annotations

import gzip
import threading
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager

import numpy as np
import numpy.typing as npt
import viser
import websockets.asyncio.server
from viser._assignable_props_api import AssignablePropsBase
from viser._messages import RunJavascriptMessage, SceneNodeUpdateMessage
from viser._scene_handles import SceneNodeHandle
from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

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


_PENDING = threading.local()  # .updates: {(id(scene api), node name): (scene api, name, {prop: value})} while open


@contextmanager
def one_message_per_node() -> Iterator[None]:
    """Within the block, this thread's property sets on scene nodes go out as one message per node at its end
    (in the order the nodes were first given one; a later value of a property replaces an earlier one)."""
    _coalesce_scene_updates()
    if getattr(_PENDING, "updates", None) is not None:  # nested: the outer block sends
        yield
        return
    _PENDING.updates = pending = {}
    try:
        yield
    finally:
        _PENDING.updates = None
        for api, name, updates in pending.values():
            api._queue_scene_message(SceneNodeUpdateMessage(name, updates))  # noqa: SLF001 - stamps the owner


def _coalesce_scene_updates() -> None:
    """Make SceneNodeHandle._queue_update collect into an open `one_message_per_node` block (once per process)."""
    with _CAST_LOCK:
        original = SceneNodeHandle._queue_update  # noqa: SLF001
        if getattr(original, "coalescing", False):
            return

        def queue_update(self, name, value):
            pending = getattr(_PENDING, "updates", None)
            if pending is None:
                return original(self, name, value)
            impl = self._impl  # noqa: SLF001
            key = (id(impl.api), impl.name)
            entry = pending.get(key)
            if entry is None:
                pending[key] = (impl.api, impl.name, {name: value})
            else:
                entry[2][name] = value

        queue_update.coalescing = True  # type: ignore[attr-defined]
        queue_update.original = original  # type: ignore[attr-defined]
        SceneNodeHandle._queue_update = queue_update  # noqa: SLF001


_IN_UPDATE = threading.local()  # .open: True while this thread is in a scene_update block


@contextmanager
def scene_update(server: viser.ViserServer) -> Iterator[None]:
    """Everything queued in the block reaches the browsers together, one message per scene node, as soon as the
    block ends, waking viser's sender once (see the module's docstring)."""
    _quiet_flush_in_updates()
    buffer = server._websock_server._broadcast_buffer  # noqa: SLF001
    buffer.atomic_start()
    first = buffer.message_counter
    _IN_UPDATE.open = True
    try:
        with one_message_per_node():
            yield
    finally:
        _IN_UPDATE.open = False
        with buffer.buffer_lock:
            buffer.atomic_counter -= 1
            release = buffer.atomic_counter == 0 and buffer.message_counter != first
        if release:
            try:
                buffer.event_loop.call_soon_threadsafe(_send_now, buffer)
            except RuntimeError:  # the server's loop has closed: nobody to send to
                pass


def _send_now(buffer) -> None:
    buffer.message_event.set()  # a sender waiting for messages takes them
    buffer.flush_event.set()  # and one waiting out a window stops waiting


def _quiet_flush_in_updates() -> None:
    """Make ViserServer.flush do nothing inside a scene_update block of its thread (once per process)."""
    with _CAST_LOCK:
        original = viser.ViserServer.flush
        if getattr(original, "quiet_in_updates", False):
            return

        def flush(self) -> None:
            if not getattr(_IN_UPDATE, "open", False):
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
        impl.api._queue_scene_message(SceneNodeUpdateMessage(impl.name, updates))  # noqa: SLF001 - stamps the owner


class BodyPoses:
    """Puts an MjData's body poses (world frame) into a ViserMujocoScene's handles, as its update_from_mjdata does."""

    def __init__(self, scene) -> None:
        self.scene = scene
        self.entries = self._entries(scene)  # None: mjviser's own update

    @staticmethod
    def _entries(scene) -> list | None:
        try:
            if (scene._any_decor_visible() or scene._show_convex_hull  # noqa: SLF001
                    or scene.camera_tracking_enabled or scene.num_envs != 1):
                return None
            entries = [(g.handle, np.asarray(g.body_ids), None if g.mocap_ids is None else np.asarray(g.mocap_ids))
                       for g in scene._mesh_groups]  # noqa: SLF001
            entries += [(h, np.array([body]), None) for (body, _), h in scene.site_handles_by_group.items()]
        except AttributeError:
            return None
        return entries

    def update(self, data) -> None:
        if self.entries is None:
            self.scene.update_from_mjdata(data)
            return
        for handle, bodies, mocaps in self.entries:
            if not handle.visible:
                continue
            if mocaps is None:
                set_arrays(handle, batched_positions=data.xpos[bodies], batched_wxyzs=data.xquat[bodies])
            else:
                set_arrays(handle, batched_positions=data.mocap_pos[mocaps], batched_wxyzs=data.mocap_quat[mocaps])
