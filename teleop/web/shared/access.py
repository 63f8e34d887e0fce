"""Who may open a served session: a token on every page request and websocket upgrade.

viser 1.1 serves its page and its websocket from one `websockets` server with
no login and no Origin check, so on any host but loopback anyone who can reach
the port could watch and drive the robot. A session listening elsewhere
therefore requires a secret token (`--token`, `TELEOP_TOKEN`, or a random one),
printed in the URL as `?token=...`.

Where the token travels:
- the page request carries it in the query (`/?token=...`); the answer sets a
  cookie (`HttpOnly`, `SameSite=Strict`, named per port because cookies are
  per host, not per port), so the page's own later requests and its
  websockets, which viser opens at the bare URL without the query, carry it
  too. A cookie is sent by the browser on every same-origin request whatever
  the page does, which is why it was chosen over checking `Referer` (dropped by
  privacy settings and referrer policies) or rewriting viser's client;
- scripts may put it in the query of any request, websockets included.

A request without the right token gets HTTP 403, websocket upgrades included,
before viser sees it; so does a browser's websocket opened by another site's
page (its Origin is not this server), viser's own included: on an open loopback
server that is what keeps a web page from driving the session or saving files.
Every server of ours asks this gate: the viser pages (`teleop serve`, the replay viewer) through
teleop.web.viser_internals.guarded_start.start_guarded, which puts it in front of viser's handler
(and routes the page's input channel on the same port, so one SSH tunnel is enough; if a viser
release stopped starting through the wrapped call, starting fails rather than serving without the
check), and the stdlib servers (the review page, the campaign lobby) through
teleop.web.shared.stdlib_http. The rules themselves are plain Python here: importing this module
loads neither viser nor websockets (a request is anything with a `path` and `headers.get_all`,
websockets' `Request` as the servers build it).

Two more checks, as Jupyter's server makes them:
- DNS rebinding: a web page can make its own name resolve to 127.0.0.1 and then talk to a
  loopback server as "same origin" (its Origin and the Host it sends are equal). So a server
  bound to loopback without a token (`local_only`) answers only requests whose Host is a
  loopback name or address (`localhost`, `127.0.0.1`, `[::1]`, any port: an SSH tunnel's
  local port included) and refuses the rest, websockets included, with 403 and one line.
  A token, or a host bound elsewhere on purpose (`--host 0.0.0.0 --no-token` behind a
  reverse proxy), leaves Host alone.
- Guessing: after `THROTTLE_FAILS` wrong tokens within `THROTTLE_WINDOW_S` from one client
  address, every request from it that carries a token gets 429 for `THROTTLE_BLOCK_S`, the
  token unchecked (`TokenThrottle`). Requests without a token never count.
"""

from __future__ import annotations

import hmac
import os
import re
import secrets
import sys
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING
from urllib.parse import parse_qs, quote, urlsplit

from teleop.errors import UsageError
from teleop.web.shared.net import exposure_warning, is_loopback, page_url, remote_hint

if TYPE_CHECKING:
    from websockets.http11 import Request

TOKEN_ENV = "TELEOP_TOKEN"
TOKEN_PATTERN = re.compile(r"[A-Za-z0-9._~-]{8,128}")  # goes into URLs and cookies unescaped
COOKIE_PREFIX = "teleop_token_"
THROTTLE_FAILS = 10  # wrong tokens from one client address ...
THROTTLE_WINDOW_S = 1.0  # ... within this many seconds ...
THROTTLE_BLOCK_S = 5.0  # ... and its requests carrying a token get 429 for this long
FORBIDDEN_TOKEN = "403 Forbidden: this server needs its token (open the URL that teleop printed, with ?token=...)"
TOO_MANY = "429 Too Many Requests: too many wrong tokens from this address; wait a few seconds"


def resolve_token(host: str, token: str | None = None, no_token: bool = False,
                  environ: Mapping[str, str] | None = None) -> str | None:
    """The token a session on `host` requires, or None when it is open.

    An explicit token (`token`, else the TELEOP_TOKEN environment variable) is
    always required, even on loopback; with neither, loopback stays open (as
    before tokens existed) and any other host gets a random token. `no_token`
    opens any host (the caller warns) and wins over the environment, but not
    over an explicit `token`: asking for both is a usage error.
    """
    environ = os.environ if environ is None else environ
    if token is not None and no_token:
        raise UsageError("--token and --no-token contradict each other: give one")
    if no_token:
        return None
    source = "--token"
    if token is None and environ.get(TOKEN_ENV):
        token, source = environ[TOKEN_ENV], TOKEN_ENV
    if token is not None:
        if not TOKEN_PATTERN.fullmatch(token):
            raise UsageError(f"{source}: a token is 8 to 128 characters from A-Z a-z 0-9 . _ ~ -")
        return token
    return None if is_loopback(host) else secrets.token_urlsafe(18)


def url_with_token(url: str, token: str | None) -> str:
    """The page URL to print: `http://host:port/?token=...`, or `http://host:port/phone?token=...` for a page
    of its own (its path kept as served: `/phone/` is not `/phone`); unchanged without a token."""
    if token is None:
        return url
    root = urlsplit(url).path in ("", "/")
    return f"{url.rstrip('/')}/?token={quote(token, safe='')}" if root else f"{url}?token={quote(token, safe='')}"


def announce(host: str, port: int, token: str | None, what: str, reach: str, log: Callable[[str], None]) -> None:
    """Say where a started page is: the warning (stderr) when a non-loopback host has no token (`reach`: what
    anyone could do there), the URL to open with its token, for `what`, and how to open it from another machine."""
    warning = exposure_warning(host, port, reach) if token is None else None
    if warning:
        print(warning, file=sys.stderr)
    log(f"open {url_with_token(page_url(host, port), token)} in a browser to {what} (Ctrl-C to stop)")
    hint = remote_hint(host)
    if hint:
        log(hint)


def local_host_header(host: str | None) -> bool:
    """Whether a request's Host header names this machine by a loopback name or address (any port):
    `localhost`, `127.0.0.1` (any of 127.0.0.0/8), `[::1]`. Anything else, or none, is not."""
    if not host:
        return False
    host = host.strip()
    if host.startswith("["):
        end = host.find("]")
        name, rest = (host[1:end], host[end + 1:]) if end > 0 else ("", "")
    else:
        name, colon, rest = host.partition(":")
        rest = colon + rest
    if rest and not (rest[0] == ":" and rest[1:].isdigit()):
        return False
    return name != "" and is_loopback(name.lower().rstrip("."))


class TokenThrottle:
    """Wrong tokens counted per client address; a client past the limit is blocked for a while (thread-safe)."""

    def __init__(self, fails: int = THROTTLE_FAILS, window_s: float = THROTTLE_WINDOW_S,
                 block_s: float = THROTTLE_BLOCK_S) -> None:
        self.fails, self.window_s, self.block_s = fails, window_s, block_s
        self._failures: dict[str, list[float]] = {}  # address -> monotonic times of its recent wrong tokens
        self._blocked: dict[str, float] = {}  # address -> monotonic time its block ends
        self._lock = threading.Lock()

    def blocked(self, address: str) -> bool:
        """Whether requests from `address` that carry a token are to be refused now (429)."""
        with self._lock:
            until = self._blocked.get(address)
            if until is None:
                return False
            if time.monotonic() < until:
                return True
            del self._blocked[address]
            return False

    def failed(self, address: str) -> None:
        """Count one wrong token from `address`; the limit-th within the window blocks it."""
        now = time.monotonic()
        with self._lock:
            recent = [t for t in self._failures.get(address, ()) if now - t < self.window_s]
            recent.append(now)
            if len(recent) >= self.fails:
                self._blocked[address] = now + self.block_s
                recent = []
            self._failures[address] = recent
            if len(self._failures) > 4096:  # many addresses: forget the quiet ones
                self._failures = {a: ts for a, ts in self._failures.items() if ts and now - ts[-1] < self.window_s}


@dataclass
class Gate:
    """The checks for one server: its token (`token=None` lets every request through), the loopback Host
    rule when it is open on loopback (`local_only`), and the wrong-token throttle. `port` names the cookie;
    a server that binds port 0 sets it once it knows its port."""

    token: str | None
    port: int
    local_only: bool = False
    throttle: TokenThrottle = field(default_factory=TokenThrottle, repr=False, compare=False)

    @classmethod
    def for_server(cls, host: str, port: int, token: str | None) -> "Gate":
        """The gate of a server listening on `host`: Host is checked when it is loopback and has no token."""
        return cls(token, port, local_only=token is None and is_loopback(host))

    def host_allowed(self, host_header: str | None) -> bool:
        """False for a request a loopback-only server must refuse (its Host is not a loopback name)."""
        return not self.local_only or local_host_header(host_header)

    def carries_token(self, request: Request) -> bool:
        """Whether a request brings any token (query or this server's cookie): only those count and are throttled."""
        return self.query_token(request) is not None or self.cookie_token(request) is not None

    @property
    def cookie_name(self) -> str:
        return f"{COOKIE_PREFIX}{self.port}"

    def query_token(self, request: Request) -> str | None:
        values = parse_qs(urlsplit(request.path).query).get("token")
        return values[0] if values else None

    def cookie_token(self, request: Request) -> str | None:
        for header in request.headers.get_all("Cookie"):
            for part in header.split(";"):
                name, eq, value = part.strip().partition("=")
                if eq and name == self.cookie_name:
                    return value.strip().strip('"')
        return None

    def _matches(self, candidate: str | None) -> bool:
        return (self.token is not None and candidate is not None
                and hmac.compare_digest(candidate.encode("utf-8", "replace"), self.token.encode()))

    def allows(self, request: Request) -> bool:
        """True when no token is required or the request carries the right one (query or cookie)."""
        if self.token is None:
            return True
        return self._matches(self.query_token(request)) or self._matches(self.cookie_token(request))

    def set_cookie(self) -> str:
        """The Set-Cookie value that lets the page's later requests and websockets in."""
        return f"{self.cookie_name}={self.token}; Path=/; HttpOnly; SameSite=Strict"

    def wants_cookie(self, request: Request) -> bool:
        """A page request that brought the token in its query (so the browser should keep it)."""
        return self.token is not None and self._matches(self.query_token(request))


def same_origin(request: Request) -> bool:
    """A browser's websocket from a page of this server (its Origin names the Host asked for), or a
    non-browser client (no Origin). Keeps other web sites' pages off a channel that drives the robot."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    host = request.headers.get("Host", "")
    return urlsplit(origin).netloc.lower() == host.lower() and host != ""


def not_local_message(port: int) -> str:
    """The 403 line for a request whose Host is not loopback, on a server open to loopback only."""
    return (f"403 Forbidden: this server answers only requests to localhost or 127.0.0.1 (a page of another site "
            f"reaching it by DNS rebinding is refused); open http://127.0.0.1:{port}/\n")
