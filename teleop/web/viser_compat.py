"""Everything teleop relies on in viser and websockets beyond their public APIs, in one place.

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
from viser._messages import RunJavascriptMessage
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
