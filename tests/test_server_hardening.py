"""The servers hardened (issue 46): DNS rebinding, tokens kept out of files, wrong tokens throttled, no port
race, slow clients dropped, one render per video, liveness asked outside the lobby's lock.

Real servers and real clients throughout: `teleop serve`, `teleop replay --serve` and `teleop review` as
processes, the lobby and the review page's server in this process on real sockets, a campaign with two
session processes, raw HTTP and websocket handshakes written byte for byte.
"""

from __future__ import annotations

import base64
import http.client
import json
import os
import re
import socket
import stat
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import viser

from replay.review import listing
from teleop.campaign.file import load_campaign
from teleop.campaign.lobby import Lobby, start_lobby
from teleop.web.shared.access import THROTTLE_BLOCK_S, Gate, local_host_header
from teleop.web.review_page.server import ReviewFolder, make_handler
from teleop.web.shared.stdlib_http import READ_TIMEOUT_S, QuietServer
from tests import browser as headless
from tests.support import CAMPAIGN_ADMIN, CAMPAIGN_JOIN, ROOT, CampaignProcess, campaign_session_status, popen_cli, run_cli, wait_until

ADMIN, JOIN = "admin-token-1234", "join-token-5678"
SCRIPT = {"steps": [{"duration": 0.4, "to_body": "cube", "offset": [0, 0, 0.1], "gripper": "open"},
                    {"duration": 0.3, "move": [0, 0, -0.04]}]}


# -- helpers: raw requests -----------------------------------------------------------------

def http_get(port: int, path: str, host: str | None = None, headers: dict | None = None) -> tuple[int, bytes]:
    """GET with an explicit Host header (http.client would write 127.0.0.1's)."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=60)
    try:
        conn.putrequest("GET", path, skip_host=True)
        conn.putheader("Host", host or f"127.0.0.1:{port}")
        for key, value in (headers or {}).items():
            conn.putheader(key, value)
        conn.endheaders()
        answer = conn.getresponse()
        return answer.status, answer.read()
    finally:
        conn.close()


def websocket_status(port: int, path: str, host: str, origin: str | None, protocol: str | None = None) -> int:
    """The status a websocket handshake gets (101: upgraded), written byte for byte with the Host and Origin given."""
    key = base64.b64encode(os.urandom(16)).decode()
    lines = [f"GET {path} HTTP/1.1", f"Host: {host}", "Upgrade: websocket", "Connection: Upgrade",
             f"Sec-WebSocket-Key: {key}", "Sec-WebSocket-Version: 13"]
    if origin:
        lines.append(f"Origin: {origin}")
    if protocol:
        lines.append(f"Sec-WebSocket-Protocol: {protocol}")
    with socket.create_connection(("127.0.0.1", port), timeout=60) as sock:
        sock.sendall(("\r\n".join(lines) + "\r\n\r\n").encode())
        head = b""
        while b"\r\n" not in head:
            chunk = sock.recv(4096)
            if not chunk:
                break
            head += chunk
    return int(head.split(b" ", 2)[1])


def assert_rebinding_refused(port: int, websocket_paths: tuple[str, ...], protocol: str | None = None) -> None:
    """A page of evil.example that resolved to 127.0.0.1 is refused (HTTP and websockets); a loopback Host is served."""
    evil = f"evil.example:{port}"
    status, body = http_get(port, "/", host=evil)
    assert status == 403, (status, body[:200])
    text = body.decode()
    assert len(text.strip().splitlines()) == 1 and "localhost or 127.0.0.1" in text
    for path in websocket_paths:
        assert websocket_status(port, path, evil, f"http://{evil}", protocol) == 403, path
    for host in (f"127.0.0.1:{port}", f"localhost:{port}"):
        assert http_get(port, "/", host=host)[0] == 200, host
    for path in websocket_paths:
        assert websocket_status(port, path, f"127.0.0.1:{port}", f"http://127.0.0.1:{port}", protocol) == 101, path


@pytest.mark.unit
def test_the_loopback_host_rule_names_only_loopback():
    for good in ("localhost:8080", "127.0.0.1:9", "[::1]:80", "127.0.0.5", "LOCALHOST", "localhost."):
        assert local_host_header(good), good
    for bad in ("evil.example:8080", "127.0.0.1.evil.example:8080", "[::1]x", "localhost:abc", "", None, "10.0.0.5:80"):
        assert not local_host_header(bad), bad
    assert Gate.for_server("127.0.0.1", 1, None).local_only
    assert not Gate.for_server("127.0.0.1", 1, "a-token-123").local_only  # a token decides
    assert not Gate.for_server("0.0.0.0", 1, None).local_only  # bound elsewhere on purpose (--no-token)


# -- a recorded episode for the viewer and the review page ---------------------------------

@pytest.fixture(scope="module")
def episodes(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("hardening")
    script = work / "short.json"
    script.write_text(json.dumps(SCRIPT))
    result = run_cli("run", "--device", f"script:{script}", "--record", str(work / "eps"), "--json", timeout=180)
    assert result.returncode == 0, result.stderr[-2000:]
    return work / "eps"


class Server:
    """A `teleop ...` server command in a subprocess, ready once it printed its URL."""

    def __init__(self, args: list[str], workdir: Path) -> None:
        self.port = headless.free_port()
        self.log_file = workdir / f"server-{self.port}.log"
        self._log = open(self.log_file, "w")
        self.proc = popen_cli([*args, "--port", str(self.port)], self._log, cwd=ROOT)
        wait_until(lambda: "open http" in self.log() or self.proc.poll() is not None, 180, "the server's URL")
        assert self.proc.poll() is None, self.log()

    def log(self) -> str:
        self._log.flush()
        return self.log_file.read_text()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(2)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()


@pytest.mark.e2e
def test_rebinding_is_refused_by_serve_replay_and_review_open_on_loopback(episodes, tmp_path):
    protocol = f"viser-v{viser.__version__}"
    (episode,) = sorted(episodes.glob("*.mcap"))
    serve = headless.ServeProcess(["--device", "gizmo", "--scene", "lift"], tmp_path)
    try:
        assert not serve.status()["token_required"]
        assert_rebinding_refused(serve.port, ("/", "/teleop/input"), protocol)
    finally:
        serve.stop()
    viewer = Server(["replay", str(episode), "--serve"], tmp_path)
    try:
        assert "?token=" not in viewer.log()
        assert_rebinding_refused(viewer.port, ("/",), protocol)
    finally:
        viewer.stop()
    review = Server(["review", str(episodes)], tmp_path)
    try:
        assert_rebinding_refused(review.port, ())
        evil = f"evil.example:{review.port}"
        assert http_get(review.port, "/api/episodes", host=evil)[0] == 403  # the API too, not only the page
        conn = http.client.HTTPConnection("127.0.0.1", review.port, timeout=60)
        body = json.dumps({"episode": episode.name, "verdict": "accept"})
        conn.putrequest("POST", "/api/verdict", skip_host=True)
        for key, value in (("Host", evil), ("Origin", f"http://{evil}"), ("Content-Type", "application/json"),
                           ("Content-Length", str(len(body)))):
            conn.putheader(key, value)
        conn.endheaders(body.encode())
        assert conn.getresponse().status == 403  # a rebinding page cannot write a verdict
        conn.close()
        assert not list(episodes.glob("*.verdict.json"))
    finally:
        review.stop()


# -- the lobby and the review page in this process -----------------------------------------

@pytest.fixture
def lobby(tmp_path) -> Iterator[tuple[Lobby, int]]:
    path = tmp_path / "c.toml"
    path.write_text('name = "c"\nout = "o"\n[[task]]\nscene = "lift"\nepisodes = 2\n')
    lobby = Lobby(load_campaign(path), "127.0.0.1", ADMIN, JOIN)
    server = start_lobby(lobby, 0)
    yield lobby, server.server_address[1]
    server.shutdown()
    server.server_close()


@pytest.fixture
def review_server(episodes) -> Iterator[tuple[QuietServer, int]]:
    token = "review-token-123"
    server = QuietServer(("127.0.0.1", 0), make_handler(ReviewFolder(episodes), Gate.for_server("127.0.0.1", 0, token), "ana"))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server, server.server_address[1]
    server.shutdown()
    server.server_close()


def statuses(port: int, paths: list[str]) -> list[int]:
    """The status of each GET, one connection each (as a guessing script would send them)."""
    return [http_get(port, path)[0] for path in paths]


def assert_throttled(port: int, wrong: str, right: str, public: str | None = None) -> None:
    """50 wrong tokens in a second: 403 ten times, then 429 (the token unchecked, the right one too) for 5 s;
    a request with no token is never counted nor refused for it; the right token works once the 5 s are over."""
    started = time.monotonic()
    got = statuses(port, [wrong] * 50)
    assert time.monotonic() - started < 5.0, "the 50 requests should have taken well under the block"
    assert got[:10] == [403] * 10 and got[10:] == [429] * 40, got
    blocked_at = time.monotonic()
    assert statuses(port, [right]) == [429]  # blocked: not even checked
    if public is not None:
        assert statuses(port, [public]) == [200]  # needs no token: never blocked
    time.sleep(max(0.0, blocked_at + THROTTLE_BLOCK_S + 0.3 - time.monotonic()))
    assert statuses(port, [right]) == [200]


@pytest.mark.e2e  # waits out real seconds (the block, the read deadline)
def test_wrong_tokens_at_the_lobby_are_throttled(lobby):
    _, port = lobby
    assert_throttled(port, "/api/status?token=wrong-token-0", f"/api/status?token={ADMIN}", public="/static/teleop.css")


@pytest.mark.e2e  # waits out real seconds (the block, the read deadline)
def test_wrong_tokens_at_the_review_page_are_throttled(review_server):
    _, port = review_server
    assert_throttled(port, "/api/info?token=wrong-token-0", "/api/info?token=review-token-123")


@pytest.mark.e2e
def test_wrong_tokens_at_a_session_page_are_throttled(episodes, tmp_path):
    (episode,) = sorted(episodes.glob("*.mcap"))
    viewer = Server(["replay", str(episode), "--serve", "--token", "viewer-token-99"], tmp_path)
    try:
        assert_throttled(viewer.port, "/?token=wrong-token-0", "/?token=viewer-token-99")
    finally:
        viewer.stop()


@pytest.mark.unit
def test_the_stylesheet_needs_no_token_and_requests_without_one_never_count(lobby):
    _, port = lobby
    got = statuses(port, ["/api/status"] * 15 + ["/static/teleop.css"] * 5)  # no token: 403, never 429
    assert got == [403] * 15 + [200] * 5, got
    status, css = http_get(port, "/static/teleop.css")
    assert status == 200 and b"{" in css


def _wait_closed(sock: socket.socket, limit_s: float) -> float:
    """Seconds until the server closes `sock` (it reads b'' or a reset), at most `limit_s`."""
    started = time.monotonic()
    sock.settimeout(limit_s)
    try:
        while sock.recv(4096):
            pass
    except ConnectionResetError:
        pass
    except TimeoutError:
        return limit_s
    return time.monotonic() - started


@pytest.mark.e2e  # waits out real seconds (the block, the read deadline)
def test_a_silent_client_and_a_byte_a_second_are_dropped_while_others_are_served(lobby, review_server):
    _, lobby_port = lobby
    _, review_port = review_server
    limit = READ_TIMEOUT_S + 8.0
    silent = [socket.create_connection(("127.0.0.1", p)) for p in (lobby_port, review_port)]
    trickle = socket.create_connection(("127.0.0.1", lobby_port))
    stop = threading.Event()

    def drip() -> None:  # "GET /api/status?token=..." a byte a second: never a whole request
        for byte in b"GET /api/status?token=" + ADMIN.encode():
            if stop.wait(1.0):
                return
            try:
                trickle.sendall(bytes([byte]))
            except OSError:
                return

    threading.Thread(target=drip, daemon=True).start()
    try:
        started = time.monotonic()
        served = statuses(lobby_port, [f"/api/status?token={ADMIN}"]) + statuses(review_port, ["/api/info?token=review-token-123"])
        assert served == [200, 200] and time.monotonic() - started < 5.0  # the held connections hold no one up
        waits = [_wait_closed(s, limit) for s in silent] + [_wait_closed(trickle, limit)]
        assert all(w < limit for w in waits), waits  # each dropped by the server within its read deadline
    finally:
        stop.set()
        for s in [*silent, trickle]:
            s.close()


@pytest.mark.e2e
def test_two_requests_for_one_uncached_video_render_it_once_and_ranges_are_served(review_server, episodes):
    _, port = review_server
    (episode,) = sorted(episodes.glob("*.mcap"))
    for cached in (episodes / listing.CACHE_DIR).glob("*.mp4*"):
        cached.unlink()
    before = listing.videos_rendered
    path = f"/video/{episode.name}.mp4?token=review-token-123"
    answers: list[tuple[int, bytes]] = []
    threads = [threading.Thread(target=lambda: answers.append(http_get(port, path))) for _ in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(300)
    assert [a[0] for a in answers] == [200, 200] and answers[0][1] == answers[1][1] and len(answers[0][1]) > 1000
    assert listing.videos_rendered == before + 1
    whole = answers[0][1]
    status, part = http_get(port, path, headers={"Range": "bytes=100-299"})
    assert status == 206 and part == whole[100:300]
    status, tail = http_get(port, path, headers={"Range": "bytes=-50"})
    assert status == 206 and tail == whole[-50:]
    assert http_get(port, path, headers={"Range": f"bytes={len(whole) + 10}-"})[0] == 416
    assert listing.videos_rendered == before + 1  # ranges read the cached file


@pytest.mark.unit
def test_a_slow_session_liveness_check_holds_no_lock(lobby):
    """A Ray session's liveness is a call to its node: a slow node must not stall joins behind the lobby's lock."""
    lobby_, _ = lobby

    class SlowNodeSession:  # what the lobby asks of a session (sessions.LiveSession / ray_sessions.RaySession)
        known_live = True

        def __init__(self, operator: str) -> None:
            self.spec = type("Spec", (), {"operator": operator})()
            self.id = operator

        @property
        def live(self) -> bool:
            time.sleep(1.5)  # a node that answers slowly
            return True

    lobby_.sessions.all.extend([SlowNodeSession("ana")])
    results: list[int] = []

    def join() -> None:
        try:
            lobby_.join(JOIN, {"name": "ana"}, "127.0.0.1")
        except Exception as exc:  # noqa: BLE001 - Refused: ana is already in a live session
            results.append(getattr(exc, "status", 0))

    started = time.monotonic()
    threads = [threading.Thread(target=join) for _ in range(3)]
    for t in threads:
        t.start()
    held = lobby_.sessions.known_live()  # no call to the slow node: answers at once, even now
    assert time.monotonic() - started < 1.0 and [s.id for s in held] == ["ana"]
    for t in threads:
        t.join(30)
    assert results == [409, 409, 409]
    assert time.monotonic() - started < 4.0  # three checks at once (1.5 s each), not one after another (4.5 s)
    lobby_.sessions.all.clear()


# -- a campaign with two sessions: no token in any file, secrets 0600, ports bound by the sessions ----

@pytest.mark.e2e
def test_a_campaign_writes_no_token_anywhere_and_keeps_its_files_private(tmp_path):
    out = tmp_path / "out"
    (tmp_path / "c.toml").write_text(f'name = "c"\nout = "{out}"\noperators = ["ana", "bo"]\n'
                                     '[[task]]\nscene = "lift"\nepisodes = 3\n')
    campaign = CampaignProcess(tmp_path / "c.toml")
    try:
        invites = dict(re.findall(r"invite for (\w+): http://\S+/join\?token=([A-Za-z0-9_-]+)", campaign.log()))
        assert set(invites) == {"ana", "bo"}
        joined = []
        for name in ("ana", "bo"):
            status, answer = campaign.ask("POST", f"/api/join?token={invites[name]}", {"name": name})
            assert status == 200, (answer, campaign.log())
            joined.append(answer)
        for j in joined:
            st = campaign_session_status(out, j["session"])
            port = int(re.search(r":(\d+)/", j["url"]).group(1))
            assert st["port"] == port > 0  # the session bound it (port 0) and said which
            assert http_get(port, f"/?token={j['token']}")[0] == 200
        wait_until(lambda: all(campaign_session_status(out, j["session"]).get("tick", 0) > 30 for j in joined), 60,
                   "the sessions to tick")
    finally:
        campaign.stop()
    secrets = [CAMPAIGN_ADMIN, CAMPAIGN_JOIN, *invites.values(), *(j["token"] for j in joined)]
    files = [p for p in out.rglob("*") if p.is_file()]
    logs = [p for p in files if p.suffix == ".log"]
    assert len(logs) == 2 and any(p.name.endswith(".status.json") for p in files)
    for path in files:
        data = path.read_bytes()
        for secret in secrets:
            assert secret.encode() not in data, f"a token in {path.relative_to(out)}"
    for log in logs:
        assert "open http" in log.read_text()  # the session still says where it serves, without the token
    state = out / ".campaign"
    private = [state / "invites.json", *(state / "sessions").iterdir()]
    for path in private:
        assert stat.S_IMODE(path.stat().st_mode) == 0o600, path
    assert stat.S_IMODE((state / "sessions").stat().st_mode) == 0o700
