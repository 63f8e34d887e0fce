"""The lobby: where operators join a campaign and the admin watches it (stdlib HTTP, one port).

    GET  /join?token=J          the join page (an invite token opens it with the name filled in)
    POST /api/join?token=J      {"name": ...} -> 200 {"operator", "task", "instruction", "url", "xr", "token", "input"}
                                202 {"queue": place} beyond max_sessions (ask again to keep the place)
    GET  /admin?token=A         the admin page (sessions live, quotas, the queue; end, pause, resume)
    GET  /api/status?token=A    the same as JSON
    POST /api/end?token=A       {"id": session} ends that session
    POST /api/pause?token=A, /api/resume?token=A    stop and restart joining

Every request brings its token in the query (the pages pass on the one in their own
URL); after 10 wrong tokens in a second from one address, its requests carrying a token get
429 for 5 s, unchecked (teleop.web.shared.access.TokenThrottle). The stylesheet (/static/teleop.css)
needs no token. Anything wrong is a 4xx with {"error": one line}: a missing or wrong token (403),
malformed JSON or a bad name (400), a body over 4 kB (413), a name already in a live
session (409), joins faster than JOIN_RATE a second (429), joining paused (503), the
campaign complete (410). Names are checked (no markup) and escaped wherever shown.
"""

from __future__ import annotations

import hmac
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path
from urllib.parse import parse_qs, quote, urlsplit

from scenes.errors import TeleopError, first_line
from teleop.campaign.file import Campaign, CampaignTask, check_operator_name
from teleop.campaign.ledger import count_task, hourly_successes, invited, load_invites
from teleop.campaign.sessions import LiveSession, Sessions
from teleop.web.shared.access import Gate
from teleop.web.shared.input_messages import PATH as INPUT_PATH
from teleop.web.shared.stdlib_http import STYLESHEET_PATH, GatedHandler, QuietServer, Refused, TokenRefused

MAX_BODY = 4096  # bytes of a request body
JOIN_RATE, JOIN_BURST = 20.0, 40.0  # joins a second, and the burst allowed, over all clients
QUEUE_STALE_S = 30.0  # a queued operator who has not asked again for this long loses the place
PAGES = Path(__file__).with_name("pages")


@dataclass
class Bucket:
    """A token bucket: at most `rate` a second on average, `burst` at once."""

    rate: float
    burst: float
    level: float = 0.0
    stamp: float = 0.0

    def __post_init__(self) -> None:
        self.level, self.stamp = self.burst, time.monotonic()
        self._lock = threading.Lock()

    def take(self) -> bool:
        with self._lock:
            now = time.monotonic()
            self.level = min(self.burst, self.level + (now - self.stamp) * self.rate)
            self.stamp = now
            if self.level < 1.0:
                return False
            self.level -= 1.0
            return True


class Lobby:
    """The campaign's state behind the HTTP handlers: who is in, who waits, what is done."""

    def __init__(self, campaign: Campaign, host: str, admin_token: str, join_token: str,
                 ray_address: str | None = None) -> None:
        self.campaign = campaign
        self.host = host
        self.admin_token, self.join_token = admin_token, join_token
        self.invites = load_invites(campaign.out) if not campaign.open else {}
        self.sessions = Sessions(campaign, host, ray_address)
        self.paused = False
        self.queue: OrderedDict[str, float] = OrderedDict()  # operator -> when they last asked
        self.bucket = Bucket(JOIN_RATE, JOIN_BURST)
        self.gate = Gate(admin_token, 0)  # the lobby checks its tokens itself; the gate's throttle counts wrong ones
        self._lock = threading.Lock()  # joins decide one at a time (slots, names, the queue)
        for task in campaign.tasks:  # no session writes yet: every file on disk is whole, counted at once after a restart
            count_task(campaign.out, task.name, settle=False)

    # -- counts ------------------------------------------------------------------
    @property
    def wanted_total(self) -> int:
        return sum(t.episodes for t in self.campaign.tasks)

    def counts(self) -> dict[str, object]:
        """task name -> its TaskCount, read from the episode files now."""
        return {t.name: count_task(self.campaign.out, t.name) for t in self.campaign.tasks}

    def next_task(self) -> CampaignTask | None:
        """The task with the most successful episodes still wanted (ties: file order); None when all are met."""
        counts = self.counts()
        best, left_best = None, 0
        for task in self.campaign.tasks:
            left = task.episodes - counts[task.name].successes
            if left > left_best:
                best, left_best = task, left
        return best

    # -- tokens ------------------------------------------------------------------
    def is_admin(self, token: str | None) -> bool:
        return token is not None and hmac.compare_digest(token.encode("utf-8", "replace"), self.admin_token.encode())

    def joiner(self, token: str | None) -> str | None:
        """Who a join token admits: "" for anyone (the open join token), an invitee's name, or None."""
        if token is None:
            return None
        if self.campaign.open and hmac.compare_digest(token.encode("utf-8", "replace"), self.join_token.encode()):
            return ""
        return invited(self.invites, token)

    # -- joining -----------------------------------------------------------------
    def join(self, token: str | None, body: dict, host: str) -> tuple[HTTPStatus, dict]:
        """A join request: a session (200), a place in the queue (202), or Refused."""
        who = self.joiner(token)
        if who is None:
            raise TokenRefused("this join link's token is not valid for this campaign")
        if not self.bucket.take():
            raise Refused(HTTPStatus.TOO_MANY_REQUESTS, "too many join requests; try again in a second")
        raw = body.get("name", who) if who == "" else body.get("name") or who
        try:
            name = check_operator_name(raw)
        except ValueError as exc:
            raise Refused(HTTPStatus.BAD_REQUEST, f"name: {exc}") from None
        if who and name != who:
            raise Refused(HTTPStatus.FORBIDDEN, "this invite is for another operator")
        self.sessions.live()  # each session's liveness asked now, outside the lock (a Ray node may be slow)
        with self._lock:
            live = self.sessions.known_live()  # no blocking call under the lock: joins decide one at a time
            if self.paused:
                raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, "joining is paused by the campaign's admin; try later")
            if any(s.spec.operator == name for s in live):
                raise Refused(HTTPStatus.CONFLICT, f"{name!r} is already in a live session (one session per operator)")
            task = self.next_task()
            if task is None:
                self.queue.pop(name, None)
                raise Refused(HTTPStatus.GONE, "the campaign has all the episodes it wants; thank you")
            now = time.monotonic()
            for stale in [n for n, seen in self.queue.items() if now - seen > QUEUE_STALE_S]:
                del self.queue[stale]
            free = self.campaign.max_sessions - len(live)
            ahead = list(self.queue).index(name) if name in self.queue else len(self.queue)
            if ahead >= free:
                self.queue[name] = now
                return HTTPStatus.ACCEPTED, {"queue": list(self.queue).index(name) + 1}
            self.queue.pop(name, None)
            try:
                session = self.sessions.start(name, task, self.wanted_total)
            except TeleopError as exc:
                raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, f"the session could not start: {first_line(exc)}") from None
        self.sessions.wait_ready(session)
        if not session.ready():
            why = session.last_log_line() or "it did not start"
            raise Refused(HTTPStatus.SERVICE_UNAVAILABLE, f"the session could not start: {why}")
        return HTTPStatus.OK, self.joined(session, task, host)

    def joined(self, session: LiveSession, task: CampaignTask, host: str) -> dict:
        spec = session.spec
        base = f"{session.url_host(host)}:{session.port}"
        token = quote(spec.token, safe="")
        return {"operator": spec.operator, "task": task.name, "instruction": task.instruction,
                "url": f"http://{base}/?token={token}", "xr": f"http://{base}/xr?token={token}", "token": spec.token,
                "input": f"ws://{base}{INPUT_PATH}?token={token}", "session": spec.session}

    # -- admin -------------------------------------------------------------------
    def status(self, host: str) -> dict:
        counts = self.counts()
        sessions = []
        for s in list(self.sessions.all):
            live = s.live
            st = s.status() if live else None
            mine = [sum(c.by_session.get(s.id, [0, 0])[k] for c in counts.values()) for k in (0, 1)]
            task = Path(st.record_dir).name if st is not None and st.record_dir else s.spec.task  # it may have moved on
            sessions.append({
                "id": s.id, "operator": s.spec.operator, "task": task,
                "state": "live" if live else "ended", "pid": s.pid, "node": s.node,
                "realtime_factor": st.realtime_factor if st else None, "latency_ms": st.latency_ms if st else None,
                "recording": st.recording if st else None, "episodes": mine[0], "successes": mine[1],
                "minutes": round(s.minutes, 2), "url": f"http://{s.url_host(host)}:{s.port}/",
            })
        tasks = [{"task": t.name, "wanted": t.episodes, "done": counts[t.name].successes,
                  "episodes": counts[t.name].episodes} for t in self.campaign.tasks]
        return {"campaign": self.campaign.name, "sessions": sessions, "tasks": tasks, "queue": list(self.queue),
                "paused": self.paused, "wanted": self.wanted_total,
                "done": sum(min(t["done"], t["wanted"]) for t in tasks), "max_sessions": self.campaign.max_sessions,
                "timeline": hourly_successes(counts)}  # successful episodes per hour: the admin page's plot

    def end(self, session_id: object) -> dict:
        session = self.sessions.find(session_id) if isinstance(session_id, str) else None
        if session is None:
            raise Refused(HTTPStatus.NOT_FOUND, "no such session")
        threading.Thread(target=self.sessions.stop, args=(session,), daemon=True).start()
        return {"ended": session.id}


def make_handler(lobby: Lobby) -> type[GatedHandler]:
    class Handler(GatedHandler):
        server_version = "teleop-campaign"
        gate = lobby.gate
        max_body = MAX_BODY

        def _token(self) -> str | None:
            values = parse_qs(urlsplit(self.path).query).get("token")
            return values[0] if values else None

        def _host(self) -> str:
            """The host name the client used to reach the lobby (sessions are on the same host)."""
            host = self.headers.get("Host") or lobby.host
            name = urlsplit(f"//{host}").hostname or lobby.host
            return f"[{name}]" if ":" in name else name

        def _dispatch(self, method: str) -> None:
            path = urlsplit(self.path).path
            if method == "GET" and path == STYLESHEET_PATH:  # nothing secret: no token, never counted
                self.send_stylesheet()
                return
            token = self._token()
            if self.throttled(token is not None):
                return
            try:
                status, obj = self._route(method, path, token)
            except Refused as exc:
                self.send_refusal(exc)
                return
            if isinstance(obj, bytes):
                self.send_body(status, obj, "text/html; charset=utf-8")
            else:
                self.send_json(obj, status)

        def _route(self, method: str, path: str, token: str | None) -> tuple[HTTPStatus, dict | bytes]:
            if method == "POST" and path == "/api/join":
                body = self.read_json()
                return lobby.join(token, body, self._host())
            if path in ("/join", "/"):
                if lobby.joiner(token) is None:
                    raise TokenRefused("this join link's token is not valid for this campaign")
                return HTTPStatus.OK, (PAGES / "join.html").read_bytes()
            if not lobby.is_admin(token):
                raise TokenRefused("this needs the campaign's admin token")
            if method == "GET" and path == "/admin":
                return HTTPStatus.OK, (PAGES / "admin.html").read_bytes()
            if method == "GET" and path == "/api/status":
                return HTTPStatus.OK, lobby.status(self._host())
            if method == "POST" and path == "/api/end":
                return HTTPStatus.OK, lobby.end(self.read_json().get("id"))
            if method == "POST" and path in ("/api/pause", "/api/resume"):
                self.read_json()
                lobby.paused = path == "/api/pause"
                return HTTPStatus.OK, {"paused": lobby.paused}
            raise Refused(HTTPStatus.NOT_FOUND, f"no such page: {path[:100]}")

        def do_GET(self) -> None:  # noqa: N802 - http.server's name
            self._dispatch("GET")

        def do_POST(self) -> None:  # noqa: N802
            self._dispatch("POST")

    return Handler


def start_lobby(lobby: Lobby, port: int) -> QuietServer:
    """Listen on lobby.host:port and serve in a thread of its own (a thread per connection)."""
    lobby.gate.port = port
    server = QuietServer((lobby.host, port), make_handler(lobby))
    threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, name="campaign-lobby", daemon=True).start()
    return server
