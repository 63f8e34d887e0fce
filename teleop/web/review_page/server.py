"""`teleop review DIR`: one page to review a folder of episodes, served over plain HTTP.

The page (review.html, review.js) lists every episode with a thumbnail, its task,
source, success, duration, quality flags and verdict; it plays the selected
episode's video (rendered on first view by replay.review and cached beside the
episodes) with its subtask bar, and keys record verdicts (j/k move, a accept,
r reject, n note). Scripts use the same API:

- `GET /api/episodes`: the list, each row with `id`, `path`, `verdict` and `quality`;
- `POST /api/verdict` with `{"episode": id, "verdict": "accept"|"reject", "reviewer": name,
  "note": text}`: records a verdict in the episode's sidecar (replay.review.verdicts).

No viser here: a list and a <video> need a small threaded stdlib server
(teleop.web.shared.stdlib_http, shared with the campaign lobby: read deadline, JSON, Range). It
sits behind the same gate as `teleop serve` and the replay viewer (teleop.web.shared.access):
a token off loopback (query or the per-port cookie), the loopback Host rule on an open
loopback server, the wrong-token throttle, and a POST from another site's page (its
Origin is not this server) is refused.
"""

from __future__ import annotations

import getpass
import re
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from urllib.parse import unquote, urlsplit

from websockets.datastructures import Headers
from websockets.http11 import Request

from replay.episode import find_episodes
from replay.review import listing
from replay.review.verdicts import VERDICTS, write_verdict
from scenes.errors import TeleopError, first_line
from teleop.errors import UsageError
from teleop.web.shared.access import FORBIDDEN_TOKEN, Gate, announce, resolve_token, same_origin
from teleop.web.shared.net import check_port_free
from teleop.web.shared.stdlib_http import STYLESHEET_PATH, GatedHandler, QuietServer, Refused

HERE = Path(__file__).resolve().parent
PAGES = {"/": ("review.html", "text/html; charset=utf-8"), "/review.js": ("review.js", "text/javascript; charset=utf-8")}
REVIEW_REACH = "see these episodes and write their verdicts"  # for the --no-token warning
MAX_BODY = 64 << 10


class ReviewFolder:
    """The folder under review: its episodes by id (file name) and their rows."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        self._lock = threading.Lock()

    def paths(self) -> dict[str, Path]:
        return {p.name: p for p in find_episodes([self.folder])}

    def path(self, episode_id: str) -> Path | None:
        return self.paths().get(episode_id)

    def rows(self, progress: Callable[[int, int], None] | None = None) -> list[dict]:
        with self._lock:  # one scoring at a time; later listings read the cache
            return listing.list_rows(self.folder, progress)

    def row(self, episode_id: str) -> dict | None:
        return next((r for r in self.rows() if r["id"] == episode_id), None)


def make_handler(review: ReviewFolder, the_gate: Gate, reviewer: str) -> type[GatedHandler]:
    gate = the_gate

    class Handler(GatedHandler):
        server_version = "teleop-review"
        gate = the_gate
        max_body = MAX_BODY

        def _request(self) -> Request:
            return Request(self.path, Headers(list(self.headers.items())))

        def send_common_headers(self, status: int) -> None:
            super().send_common_headers(status)
            if gate.token is not None and status == 200 and gate.wants_cookie(self._request()):
                self.send_header("Set-Cookie", gate.set_cookie())

        def _allowed(self) -> bool:
            """The Host rule, the throttle and the token; False once a refusal is answered."""
            if not self.host_allowed():
                return False
            request = self._request()
            carries = gate.carries_token(request)
            if self.throttled(carries):
                return False
            if not gate.allows(request):
                if carries:
                    self.token_failed()
                self.send_text(403, FORBIDDEN_TOKEN + "\n")
                return False
            return True

        def do_HEAD(self) -> None:  # noqa: N802 - http.server's name
            self.do_GET()

        def do_GET(self) -> None:  # noqa: N802
            path = unquote(urlsplit(self.path).path)
            if path == STYLESHEET_PATH:  # nothing secret: no token, never counted
                if self.host_allowed():
                    self.send_stylesheet()
                return
            if not self._allowed():
                return
            try:
                if path in PAGES:
                    name, kind = PAGES[path]
                    self.send_body(200, (HERE / name).read_bytes(), kind)
                elif path == "/api/episodes":
                    self.send_json(review.rows())
                elif path == "/api/info":
                    self.send_json({"folder": str(review.folder), "reviewer": reviewer, "verdicts": list(VERDICTS)})
                elif (m := re.fullmatch(r"/thumb/(.+)\.png", path)) and (ep := review.path(m.group(1))):
                    self.send_body(200, listing.thumbnail(ep), "image/png")
                elif (m := re.fullmatch(r"/video/(.+)\.mp4", path)) and (ep := review.path(m.group(1))):
                    self.send_file(listing.video(ep), "video/mp4")
                else:
                    self.send_refusal(Refused(404, f"{path}: not found"))
            except ConnectionError:  # the browser went away (a <video> drops ranges it no longer wants)
                self.close_connection = True
            except (TeleopError, OSError) as exc:
                self.send_refusal(Refused(500, first_line(exc)))

        def do_POST(self) -> None:  # noqa: N802
            if not self._allowed():
                return
            if not same_origin(self._request()):
                self.send_text(403, "403 Forbidden: cross-origin\n")
                return
            try:
                if urlsplit(self.path).path != "/api/verdict":
                    raise Refused(404, "not found")
                body = self.read_json()
                if not body:
                    raise Refused(400, "a JSON body is required")
                episode = review.path(str(body.get("episode", "")))
                if episode is None:
                    raise Refused(404, f"no episode {body.get('episode')!r} in {review.folder}")
                try:
                    written = write_verdict(episode, body.get("verdict"), str(body.get("reviewer") or ""),
                                            str(body.get("note") or ""))
                except TeleopError as exc:
                    raise Refused(400 if isinstance(exc, ValueError) else 500, first_line(exc)) from None
            except Refused as refused:
                self.send_refusal(refused)
                return
            self.send_json({"episode": episode.name, **written})

    return Handler


def serve_review(folder: str | Path, host: str = "127.0.0.1", port: int = 8080, token: str | None = None,
                 no_token: bool = False, stop: threading.Event | None = None,
                 log: Callable[[str], None] | None = None) -> int:
    """Score the folder's episodes (cached), then serve the review page until `stop` is set or Ctrl-C."""
    log = log or (lambda line: print(line, flush=True))
    folder = Path(folder)
    if not folder.is_dir():
        raise UsageError(f"{folder}: not a folder of episodes")
    token = resolve_token(host, token, no_token)
    check_port_free(host, port)
    review = ReviewFolder(folder)
    total = len(review.paths())
    if total == 0:
        raise UsageError(f"{folder}: no episode files (.mcap, .hdf5) in it")

    def progress(done: int, count: int) -> None:
        if done == count or done % 25 == 0:
            print(f"scored {done}/{count} episodes", file=sys.stderr, flush=True)

    review.rows(progress)
    try:
        server = QuietServer((host, port), make_handler(review, Gate.for_server(host, port, token), getpass.getuser()))
    except OSError as exc:
        raise UsageError(f"cannot listen on {host}:{port}: {exc.strerror or exc}") from None
    server.daemon_threads = True
    announce(host, port, token, f"review {total} episodes", REVIEW_REACH, log)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.2}, name="review-http",
                              daemon=True)
    thread.start()
    waiter = stop if stop is not None else threading.Event()
    try:
        while not waiter.wait(0.5):
            pass
    except KeyboardInterrupt:
        pass
    finally:
        server.shutdown()
        server.server_close()
        listing.wait_for_renders()
    return 0

