"""`teleop review DIR`: one page to review a folder of episodes, served over plain HTTP.

The page (review.html, review.js) lists every episode with a thumbnail, its task,
source, success, duration, quality flags and verdict; it plays the selected
episode's video (rendered on first view by replay.review and cached beside the
episodes) with its subtask bar, and keys record verdicts (j/k move, a accept,
r reject, n note). Scripts use the same API:

- `GET /api/episodes`: the list, each row with `id`, `path`, `verdict` and `quality`;
- `POST /api/verdict` with `{"episode": id, "verdict": "accept"|"reject", "reviewer": name,
  "note": text}`: records a verdict in the episode's sidecar (replay.review.verdicts).

No viser here: a list and a <video> need a small threaded stdlib server. It sits
behind the same gate as `teleop serve` and the replay viewer (teleop.web.access):
a token off loopback (query or the per-port cookie), and a POST from another
site's page (its Origin is not this server) is refused.
"""

from __future__ import annotations

import getpass
import json
import re
import sys
import threading
from collections.abc import Callable
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import unquote, urlsplit

from websockets.datastructures import Headers
from websockets.http11 import Request

from replay.episode import find_episodes
from replay.review import listing
from replay.review.verdicts import VERDICTS, write_verdict
from scenes.errors import TeleopError, first_line
from teleop.errors import UsageError
from teleop.web.access import Gate, announce, resolve_token, same_origin
from teleop.web.net import check_port_free

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


def make_handler(review: ReviewFolder, gate: Gate, reviewer: str):
    class Handler(BaseHTTPRequestHandler):
        server_version = "teleop-review"

        def log_message(self, format: str, *args) -> None:  # noqa: A002 - the stdlib's name
            pass

        def _request(self) -> Request:
            return Request(self.path, Headers(list(self.headers.items())))

        def _send(self, status: int, body: bytes, kind: str, extra: dict | None = None) -> None:
            self.send_response(status)
            self.send_header("Content-Type", kind)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            if gate.token is not None:
                self.send_header("Referrer-Policy", "no-referrer")
                if status == 200 and gate.wants_cookie(self._request()):
                    self.send_header("Set-Cookie", gate.set_cookie())
            for key, value in (extra or {}).items():
                self.send_header(key, value)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _json(self, obj, status: int = 200) -> None:
            self._send(status, json.dumps(obj).encode(), "application/json")

        def _error(self, status: int, message: str) -> None:
            self._json({"error": message}, status)

        def _allowed(self) -> bool:
            if not gate.allows(self._request()):
                self._send(403, b"403 Forbidden: this server needs its token (open the URL that teleop printed, "
                                b"with ?token=...)\n", "text/plain")
                return False
            return True

        def do_HEAD(self) -> None:
            self.do_GET()

        def do_GET(self) -> None:
            if not self._allowed():
                return
            path = unquote(urlsplit(self.path).path)
            try:
                if path in PAGES:
                    name, kind = PAGES[path]
                    self._send(200, (HERE / name).read_bytes(), kind)
                elif path == "/api/episodes":
                    self._json(review.rows())
                elif path == "/api/info":
                    self._json({"folder": str(review.folder), "reviewer": reviewer, "verdicts": list(VERDICTS)})
                elif (m := re.fullmatch(r"/thumb/(.+)\.png", path)) and (ep := review.path(m.group(1))):
                    self._send(200, listing.thumbnail(ep), "image/png")
                elif (m := re.fullmatch(r"/video/(.+)\.mp4", path)) and (ep := review.path(m.group(1))):
                    self._file(listing.video(ep), "video/mp4")
                else:
                    self._error(404, f"{path}: not found")
            except ConnectionError:  # the browser went away (a <video> drops ranges it no longer wants)
                return
            except (TeleopError, OSError) as exc:
                self._error(500, first_line(exc))

        def _file(self, file: Path, kind: str) -> None:
            """A file, or the byte range asked for (a <video> seeks with Range requests)."""
            data = file.read_bytes()
            ranged = re.fullmatch(r"bytes=(\d*)-(\d*)", self.headers.get("Range", "").strip())
            if ranged and (ranged.group(1) or ranged.group(2)):
                size = len(data)
                if ranged.group(1):
                    start = int(ranged.group(1))
                    end = min(int(ranged.group(2)) if ranged.group(2) else size - 1, size - 1)
                else:
                    start, end = max(0, size - int(ranged.group(2))), size - 1
                if start > end or start >= size:
                    self._send(416, b"", kind, {"Content-Range": f"bytes */{size}"})
                    return
                self._send(206, data[start:end + 1], kind,
                           {"Content-Range": f"bytes {start}-{end}/{size}", "Accept-Ranges": "bytes"})
                return
            self._send(200, data, kind, {"Accept-Ranges": "bytes"})

        def do_POST(self) -> None:
            if not self._allowed():
                return
            if not same_origin(self._request()):
                self._send(403, b"403 Forbidden: cross-origin\n", "text/plain")
                return
            if urlsplit(self.path).path != "/api/verdict":
                self._error(404, "not found")
                return
            try:
                length = int(self.headers.get("Content-Length", "0"))
                if not 0 < length <= MAX_BODY:
                    raise ValueError("a JSON body is required")
                body = json.loads(self.rfile.read(length))
                if not isinstance(body, dict):
                    raise ValueError("the body must be a JSON object")
            except ValueError as exc:
                self._error(400, str(exc))
                return
            episode = review.path(str(body.get("episode", "")))
            if episode is None:
                self._error(404, f"no episode {body.get('episode')!r} in {review.folder}")
                return
            try:
                written = write_verdict(episode, body.get("verdict"), str(body.get("reviewer") or ""),
                                        str(body.get("note") or ""))
            except TeleopError as exc:
                self._error(400 if isinstance(exc, ValueError) else 500, first_line(exc))
                return
            self._json({"episode": episode.name, **written})

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
        server = ThreadingHTTPServer((host, port), make_handler(review, Gate(token, port), getpass.getuser()))
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

