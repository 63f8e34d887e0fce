"""How viser serves its page and websocket, and the hook teleop puts in front of it (the token gate, our routes).

- `wrapping_serve`: `ViserServer()` starts its one HTTP + websocket server with
  `websockets.asyncio.server.serve(handler, host, port, ..., process_request=...)`,
  looked up at call time; while the context is open that function lets us change
  the handler and `process_request` (the token gate and the input channel's route,
  teleop.web.viser_internals.guarded_start), so viser's own serving code runs unchanged behind them.
  Not process-wide: it lasts only while a `ViserServer()` is constructed inside it. The same call
  takes an `ssl` context for `teleop serve --https` (viser has no TLS option).
- `INDEX_PATHS`, `with_head_script`: viser answers its page (its
  `client/build/index.html`, one `<head>`) at `/`, gzipped when the browser accepts
  gzip; a script of ours goes first in that `<head>` (teleop.web.shared.view_quality).
- `limit_message_size`: websockets' per-connection limit on incoming messages
  (viser sets 50 MB on every connection of its server, ours included).
- `WEBSOCKET_PROTOCOL`: the subprotocol viser's server asks of a websocket client
  (the bench's pages that are not browsers).

Why viser needs these and what upstream change would retire them: the package's docstring
(teleop/web/viser_internals/__init__.py).
"""

from __future__ import annotations

import gzip
import ssl
import threading
from collections.abc import Awaitable, Callable, Iterator
from contextlib import contextmanager

import viser
import websockets.asyncio.server
from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

Handler = Callable[[ServerConnection], Awaitable[None]]
ProcessRequest = Callable[[ServerConnection, Request], "Response | None | Awaitable[Response | None]"]
ServeWrap = Callable[[Handler, "ProcessRequest | None"], "tuple[Handler, ProcessRequest | None]"]

INDEX_PATHS = ("/", "/index.html")  # where viser answers its page
WEBSOCKET_PROTOCOL = f"viser-v{viser.__version__}"  # the subprotocol a client of viser's websocket must ask for

_SERVE_LOCK = threading.Lock()  # one wrapped start at a time: the replacement is process-wide while it lasts


@contextmanager
def wrapping_serve(wrap: ServeWrap, tls: "ssl.SSLContext | None" = None) -> Iterator[list[bool]]:
    """While open, a server viser starts gets `wrap(handler, process_request)` in place of its own two, and
    serves over TLS with `tls` when given (viser has no TLS option: `teleop serve --https`); yields a list that
    gains an entry per server so started (empty: viser did not start through the call)."""
    module = websockets.asyncio.server
    original = module.serve
    wrapped: list[bool] = []

    def serve(handler: Handler, *args, process_request: ProcessRequest | None = None, **kwargs):
        wrapped.append(True)
        handler, process_request = wrap(handler, process_request)
        if tls is not None:
            kwargs["ssl"] = tls
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
