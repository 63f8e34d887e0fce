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
"""

from __future__ import annotations

import gzip
import threading
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager

import viser
import websockets.asyncio.server
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
