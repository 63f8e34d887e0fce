"""viser's server started behind the gate: `start_guarded`, where every viser page of ours starts.

viser 1.1 serves its page and its websocket from one `websockets` server with no login and no Origin
check. The gate's rules (token, loopback Host rule, wrong-token throttle) are teleop.web.shared.access's;
here they are put in front of viser's handler by wrapping the one call through which viser starts its
server (`websockets.asyncio.server.serve`) while `ViserServer` starts (serving_hooks.wrapping_serve), so
viser's own serving code is used unchanged. The same wrapper routes extra websocket paths (the page's
input channel) to our handlers on the same port, so one SSH tunnel is enough, answers our own pages
(the phone page) before viser's static files, and puts our script first in viser's page. If a viser
release stopped going through that call, starting fails rather than serving without the check.
Both viser servers, `teleop serve` and the replay viewer, start here; so viser's process-wide patches
(`install()`) are installed here too.
"""

from __future__ import annotations

import http
import inspect
import ssl
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import TypeVar
from urllib.parse import urlsplit

from websockets.asyncio.server import ServerConnection
from websockets.datastructures import Headers
from websockets.http11 import Request, Response

from teleop.web.shared.access import FORBIDDEN_TOKEN, TOO_MANY, Gate, not_local_message, same_origin
from teleop.web.viser_internals import install
from teleop.web.viser_internals.serving_hooks import INDEX_PATHS, Handler, ProcessRequest, with_head_script, wrapping_serve

T = TypeVar("T")


def _is_upgrade(request: Request) -> bool:
    return request.headers.get("Upgrade", "").lower() == "websocket"


def html_response(body: bytes) -> Response:
    """A 200 answer with an HTML page of our own (the phone page)."""
    headers = Headers([("Content-Type", "text/html; charset=utf-8"), ("Content-Length", str(len(body)))])
    return Response(http.HTTPStatus.OK, "OK", headers, body)


def guard(gate: Gate, inner: ProcessRequest | None, routes: Mapping[str, Handler],
          pages: Mapping[str, bytes] | None = None, head: bytes | None = None) -> ProcessRequest:
    """viser's `process_request` behind the token check; our websocket paths checked for Origin too,
    our own pages (path -> HTML) answered before viser's static files, and `head` (a <script>)
    put first in viser's page."""
    edited: dict[bytes, bytes] = {}

    async def process_request(connection: ServerConnection, request: Request) -> Response | None:
        if not gate.host_allowed(request.headers.get("Host")):
            return connection.respond(http.HTTPStatus.FORBIDDEN, not_local_message(gate.port))
        if gate.token is not None:
            address = str(connection.remote_address[0]) if connection.remote_address else ""
            carries = gate.carries_token(request)
            if carries and gate.throttle.blocked(address):
                return connection.respond(http.HTTPStatus.TOO_MANY_REQUESTS, TOO_MANY + "\n")
            if not gate.allows(request):
                if carries:
                    gate.throttle.failed(address)
                return connection.respond(http.HTTPStatus.FORBIDDEN, FORBIDDEN_TOKEN + "\n")
        path = urlsplit(request.path).path
        if _is_upgrade(request) and not same_origin(request):  # viser's websocket too: it drives and saves
            return connection.respond(http.HTTPStatus.FORBIDDEN, "403 Forbidden: cross-origin\n")
        if _is_upgrade(request) and path in routes:
            return None
        if not _is_upgrade(request) and pages and path in pages:
            response = html_response(pages[path])
        else:
            response = inner(connection, request) if inner is not None else None
        if inspect.isawaitable(response):
            response = await response
        if head and response is not None and response.status_code == http.HTTPStatus.OK and path in INDEX_PATHS:
            response = with_head_script(response, head, edited)
        if response is not None and gate.token is not None:
            response.headers["Referrer-Policy"] = "no-referrer"  # the token never leaves in a Referer
            response.headers["Cache-Control"] = "no-store"
            if gate.wants_cookie(request) and response.status_code == http.HTTPStatus.OK:
                response.headers["Set-Cookie"] = gate.set_cookie()
        return response

    return process_request


def route(inner: Handler, routes: Mapping[str, Handler]) -> Handler:
    """viser's websocket handler, with our paths sent to our handlers instead."""

    async def handler(connection: ServerConnection) -> None:
        target = routes.get(urlsplit(connection.request.path).path) if connection.request is not None else None
        await (target or inner)(connection)

    return handler


@contextmanager
def _guarded_serve(gate: Gate, routes: Mapping[str, Handler], pages: Mapping[str, bytes] | None = None,
                   head: bytes | None = None, tls: "ssl.SSLContext | None" = None) -> Iterator[list[bool]]:
    """While open, servers viser starts get the gate and routes; yields a list that gains an entry
    per server so wrapped (empty: the check was not installed)."""
    with wrapping_serve(lambda handler, process_request: (
            route(handler, routes), guard(gate, process_request, routes, pages, head)), tls) as wrapped:
        yield wrapped


def start_guarded(start: Callable[[], T], stop: Callable[[T], None], gate: Gate,
                  routes: Mapping[str, Handler], pages: Mapping[str, bytes] | None = None,
                  head: bytes | None = None, tls: "ssl.SSLContext | None" = None) -> T:
    """`start()` (which must start a viser server and return it) with the gate and routes installed, over TLS
    with `tls` when given.

    Raises RuntimeError (after `stop`) if the server did not start through the
    wrapped call, so a session never serves without its token check. Every app of ours
    starts its viser server here, so viser's process-wide patches are installed here too.
    """
    install()
    with _guarded_serve(gate, routes, pages, head, tls) as wrapped:
        server = start()
    if not wrapped:
        stop(server)
        raise RuntimeError("this viser version starts its server in a way teleop cannot guard; "
                           "the session token and the page input channel need viser 1.1")
    return server
