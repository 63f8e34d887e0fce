"""What the two hand-written HTTP servers (the campaign lobby, the review page) share.

Both are stdlib `ThreadingHTTPServer`s: a thread per connection, so one slow client holds
one thread, never the server. `GatedHandler` gives them, once:
- a read deadline: a request (its line, headers and body) must arrive whole within
  `READ_TIMEOUT_S` of its first byte being awaited, so a client that sends nothing, or a
  byte a second, is dropped (a per-read socket timeout alone would let a byte a second
  hold a thread for ever);
- the checks of teleop.web.shared.access: the loopback Host rule of a server open on loopback
  (DNS rebinding), and the wrong-token throttle (429, the token unchecked);
- JSON bodies with a size limit, answers as JSON, errors as `{"error": one line}`
  (`Refused`);
- files with Range: a <video> seeks with Range requests, answered by reading only the
  range asked for;
- the shared stylesheet at `STYLESHEET_PATH`, served without a token (nothing secret
  in it) and never counted as a token check.
"""

from __future__ import annotations

import io
import json
import re
import shutil
import socket
import time
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path

from teleop.web.shared.access import FORBIDDEN_TOKEN, TOO_MANY, Gate, not_local_message

READ_TIMEOUT_S = 10.0  # s for a whole request to arrive, from the moment the server starts reading it
STYLESHEET_PATH = "/static/teleop.css"
STYLESHEET_FILE = Path(__file__).resolve().parent / "static" / "teleop.css"
CHUNK = 1 << 16  # bytes a file is sent in


class Refused(Exception):
    """A request answered with a 4xx/5xx and `{"error": reason}` (one line)."""

    def __init__(self, status: HTTPStatus | int, reason: str) -> None:
        super().__init__(reason)
        self.status = HTTPStatus(status)


class TokenRefused(Refused):
    """A request that carried a wrong token: 403, and counted by the throttle."""

    def __init__(self, reason: str = FORBIDDEN_TOKEN) -> None:
        super().__init__(HTTPStatus.FORBIDDEN, reason)


class _DeadlineReader(io.RawIOBase):
    """A socket's bytes, each read given only what is left of the current request's deadline."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.deadline = time.monotonic() + READ_TIMEOUT_S

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:  # noqa: ANN001 - io's signature
        left = self.deadline - time.monotonic()
        if left <= 0:
            raise TimeoutError("the request did not arrive in time")
        self.sock.settimeout(left)
        return self.sock.recv_into(buffer)


class QuietServer(ThreadingHTTPServer):
    """A thread per connection (daemon threads), and a listen backlog for a room of clients at once
    (socketserver's default of 5 reset connections when 24 operators joined in the same second)."""

    request_queue_size = 128
    daemon_threads = True

    def handle_error(self, request, client_address) -> None:  # noqa: ANN001 - socketserver's signature
        pass  # a client that went away or timed out: nothing for the terminal


class GatedHandler(BaseHTTPRequestHandler):
    """A request handler with the deadline, the gate's checks and the JSON and file answers.

    Subclasses set `gate` (or leave it None: the lobby checks its own tokens) and write `do_GET`/`do_POST`.
    """

    gate: Gate | None = None
    max_body = 64 << 10  # bytes of a JSON body
    protocol_version = "HTTP/1.1"
    timeout = READ_TIMEOUT_S  # the socket's timeout while nothing is read (writes to a stalled client)

    def setup(self) -> None:
        super().setup()
        self._reader = _DeadlineReader(self.connection)
        self.rfile = io.BufferedReader(self._reader)

    def handle_one_request(self) -> None:
        self._reader.deadline = time.monotonic() + READ_TIMEOUT_S  # each request on a kept-alive connection anew
        try:
            super().handle_one_request()
        except (TimeoutError, socket.timeout, ConnectionError):
            self.close_connection = True

    def log_message(self, format: str, *args) -> None:  # noqa: A002 - the stdlib's name; quiet
        pass

    # -- who is asking ----------------------------------------------------------
    @property
    def client_address_key(self) -> str:
        return str(self.client_address[0]) if self.client_address else ""

    def host_allowed(self) -> bool:
        """The loopback Host rule (a server open on loopback); a refusal is answered here."""
        gate = self.gate
        if gate is None or gate.host_allowed(self.headers.get("Host")):
            return True
        self.send_text(HTTPStatus.FORBIDDEN, not_local_message(gate.port))
        return False

    def throttled(self, carries_token: bool) -> bool:
        """True (and 429 answered) when this client is blocked for wrong tokens and this request carries one."""
        gate = self.gate
        if gate is None or not carries_token or not gate.throttle.blocked(self.client_address_key):
            return False
        self.send_text(HTTPStatus.TOO_MANY_REQUESTS, TOO_MANY + "\n")
        return True

    def token_failed(self) -> None:
        if self.gate is not None:
            self.gate.throttle.failed(self.client_address_key)

    # -- answers ----------------------------------------------------------------
    def send_body(self, status: HTTPStatus | int, body: bytes, kind: str, extra: dict[str, str] | None = None) -> None:
        self.send_response(int(status))
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.send_common_headers(int(status))
        for key, value in (extra or {}).items():
            self.send_header(key, value)
        self.end_headers()
        if self.command != "HEAD":
            self.wfile.write(body)

    def send_common_headers(self, status: int) -> None:
        """Headers every answer carries: no caching, no token leaving in a Referer, no type sniffing."""
        self.send_header("Cache-Control", "no-store")
        self.send_header("Referrer-Policy", "no-referrer")
        self.send_header("X-Content-Type-Options", "nosniff")
        if status >= 400:
            self.close_connection = True  # a body left unread must not be taken for the next request

    def send_text(self, status: HTTPStatus | int, text: str) -> None:
        self.send_body(status, text.encode(), "text/plain; charset=utf-8")

    def send_json(self, obj: object, status: HTTPStatus | int = HTTPStatus.OK) -> None:
        self.send_body(status, (json.dumps(obj) + "\n").encode(), "application/json")

    def send_refusal(self, refused: Refused) -> None:
        if isinstance(refused, TokenRefused):
            self.token_failed()
        self.send_json({"error": str(refused)}, refused.status)

    def send_stylesheet(self) -> None:
        try:
            body = STYLESHEET_FILE.read_bytes()
        except OSError:
            self.send_json({"error": "no stylesheet in this installation"}, HTTPStatus.NOT_FOUND)
            return
        self.send_body(HTTPStatus.OK, body, "text/css; charset=utf-8")

    def send_file(self, file: Path, kind: str) -> None:
        """A file, or the one byte range asked for (read from disk alone: a <video> seeks with Range)."""
        size = file.stat().st_size
        start, end, status = 0, size - 1, HTTPStatus.OK
        ranged = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", "").strip())
        if ranged and (ranged.group(1) or ranged.group(2)):
            if ranged.group(1):
                start = int(ranged.group(1))
                end = min(int(ranged.group(2)) if ranged.group(2) else size - 1, size - 1)
            else:
                start, end = max(0, size - int(ranged.group(2))), size - 1
            if start > end or start >= size:
                self.send_body(HTTPStatus.REQUESTED_RANGE_NOT_SATISFIABLE, b"", kind, {"Content-Range": f"bytes */{size}"})
                return
            status = HTTPStatus.PARTIAL_CONTENT
        length = end - start + 1 if size else 0
        self.send_response(int(status))
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(length))
        self.send_header("Accept-Ranges", "bytes")
        if status == HTTPStatus.PARTIAL_CONTENT:
            self.send_header("Content-Range", f"bytes {start}-{end}/{size}")
        self.send_common_headers(int(status))
        self.end_headers()
        if self.command == "HEAD" or not length:
            return
        with open(file, "rb") as f:
            f.seek(start)
            shutil.copyfileobj(_Limited(f, length), self.wfile, CHUNK)

    # -- requests ---------------------------------------------------------------
    def read_json(self) -> dict:
        """The request's JSON object (an empty body is {}); Refused when too big, malformed or not an object."""
        try:
            length = int(self.headers.get("Content-Length") or 0)
        except ValueError:
            raise Refused(HTTPStatus.BAD_REQUEST, "bad Content-Length") from None
        if length > self.max_body or length < 0:
            raise Refused(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the request body is over {self.max_body} bytes")
        raw = self.rfile.read(length) if length else b""
        if not raw.strip():
            return {}
        try:
            body = json.loads(raw)
        except (ValueError, UnicodeDecodeError):
            raise Refused(HTTPStatus.BAD_REQUEST, "the request body is not valid JSON") from None
        if not isinstance(body, dict):
            raise Refused(HTTPStatus.BAD_REQUEST, "the request body must be a JSON object")
        return body


class _Limited(io.RawIOBase):
    """The next `left` bytes of a file, no more."""

    def __init__(self, f, left: int) -> None:  # noqa: ANN001 - any binary file
        self.f, self.left = f, left

    def read(self, size: int = -1) -> bytes:
        if self.left <= 0:
            return b""
        data = self.f.read(self.left if size < 0 else min(size, self.left))
        self.left -= len(data)
        return data
