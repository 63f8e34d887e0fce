"""Issue 35: the lobby's answers to bad input, in-process and quick (no session process starts here).

Each request below is refused before a session would start: a wrong token, a bad name,
malformed JSON, a huge body, a flood of joins, joining paused, a campaign already complete.
"""

from __future__ import annotations

import http.client
import json
from collections.abc import Iterator

import pytest

from teleop.campaign.file import load_campaign
from teleop.campaign.ledger import issue_invites
from teleop.campaign.lobby import JOIN_BURST, JOIN_RATE, Bucket, Lobby, start_lobby
from teleop.web.shared.access import TokenThrottle

ADMIN, JOIN = "admin-token-1", "join-token-1"


@pytest.fixture
def lobby(tmp_path) -> Iterator[tuple[Lobby, int]]:
    path = tmp_path / "c.toml"
    path.write_text('name = "c"\nout = "o"\n[[task]]\nscene = "lift"\nepisodes = 2\n[[task]]\nscene = "stack"\nepisodes = 3\n')
    lobby = Lobby(load_campaign(path), "127.0.0.1", ADMIN, JOIN)
    server = start_lobby(lobby, 0)
    yield lobby, server.server_address[1]
    server.shutdown()
    server.server_close()
    assert not lobby.sessions.all  # nothing here ever started a session


def ask(port: int, method: str, path: str, body: bytes | None = None, headers: dict | None = None) -> tuple[int, dict | str]:
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.request(method, path, body=body, headers=headers or {})
        response = conn.getresponse()
        data = response.read().decode()
        kind = response.getheader("Content-Type", "")
    finally:
        conn.close()
    return response.status, json.loads(data) if kind.startswith("application/json") else data


def join(port: int, body: object, token: str = JOIN) -> tuple[int, dict]:
    return ask(port, "POST", f"/api/join?token={token}", json.dumps(body).encode(), {"Content-Type": "application/json"})


def one_line(answer: dict) -> str:
    assert set(answer) == {"error"} and answer["error"] and "\n" not in answer["error"]
    return answer["error"]


def test_bad_joins_get_a_4xx_and_one_line(lobby):
    _, port = lobby
    status, answer = join(port, {"name": "ana"}, token="wrong-token")
    assert status == 403 and "token" in one_line(answer)
    status, answer = join(port, {"name": "<img src=x onerror=alert(1)>"})
    assert status == 400 and "no markup" in one_line(answer)
    status, answer = join(port, {"name": "x" * 10_000})
    assert status == 413 and "over 4096 bytes" in one_line(answer)  # the body itself is over the limit
    status, answer = join(port, {"name": "x" * 1_000})
    assert status == 400 and "at most 64" in one_line(answer)
    status, answer = join(port, {})
    assert status == 400 and "name" in one_line(answer)
    status, answer = ask(port, "POST", f"/api/join?token={JOIN}", b'{"name": "ana"', {"Content-Type": "application/json"})
    assert status == 400 and "not valid JSON" in one_line(answer)
    status, answer = ask(port, "POST", f"/api/join?token={JOIN}", b'["ana"]')
    assert status == 400 and "JSON object" in one_line(answer)


def test_admin_pages_need_the_admin_token_and_the_join_token_is_not_it(lobby):
    lobby_, port = lobby
    lobby_.gate.throttle = TokenThrottle(fails=1000)  # this test counts 403s: the throttle's 429s have tests of their own
    for token in ("", JOIN, "nope-nope"):
        for method, path in (("GET", "/api/status"), ("GET", "/admin"), ("POST", "/api/pause"), ("POST", "/api/end")):
            status, answer = ask(port, method, f"{path}?token={token}")
            assert status == 403 and "admin token" in one_line(answer), (method, path, token)
    assert ask(port, "GET", f"/join?token={ADMIN}")[0] == 403  # the admin token is no join link either
    status, page = ask(port, "GET", f"/join?token={JOIN}")
    assert status == 200 and "<form" in page
    status, answer = ask(port, "GET", f"/api/status?token={ADMIN}")
    timeline = answer.pop("timeline", None)  # successful episodes per hour for the admin page's plot: none yet
    assert timeline is not None and timeline["campaign"] == [0] and timeline["operators"] == {}
    assert timeline["tasks"] == {"lift": [0], "stack": [0]} and timeline["hour_s"] == 3600
    assert status == 200 and answer == {
        "campaign": "c", "sessions": [], "tasks": [{"task": "lift", "wanted": 2, "done": 0, "episodes": 0},
                                            {"task": "stack", "wanted": 3, "done": 0, "episodes": 0}],
        "queue": [], "paused": False, "wanted": 5, "done": 0, "max_sessions": 4}
    assert ask(port, "POST", f"/api/end?token={ADMIN}", b'{"id": "s1"}')[0] == 404


def test_joining_paused_is_refused_until_resumed(lobby):
    lobby_, port = lobby
    assert ask(port, "POST", f"/api/pause?token={ADMIN}") == (200, {"paused": True})
    status, answer = join(port, {"name": "ana"})
    assert status == 503 and "paused" in one_line(answer)
    assert ask(port, "POST", f"/api/resume?token={ADMIN}") == (200, {"paused": False})
    assert not lobby_.paused


def test_the_join_bucket_allows_a_burst_then_its_rate(monkeypatch):
    now = [100.0]
    monkeypatch.setattr("teleop.campaign.lobby.time.monotonic", lambda: now[0])
    bucket = Bucket(JOIN_RATE, JOIN_BURST)
    assert sum(bucket.take() for _ in range(int(JOIN_BURST) + 10)) == int(JOIN_BURST)
    now[0] += 1.0  # one second refills JOIN_RATE tokens, no more
    assert sum(bucket.take() for _ in range(int(JOIN_BURST))) == int(JOIN_RATE)
    now[0] += 3600.0  # a long quiet spell refills the burst, never beyond it
    assert sum(bucket.take() for _ in range(int(JOIN_BURST) + 10)) == int(JOIN_BURST)


def test_a_flood_of_joins_is_cut_to_the_rate(lobby):
    lobby_, port = lobby
    lobby_.paused = True  # every join that passes the rate is then refused before a session starts
    # the lobby's own bucket, refilled slowly: a loaded machine's slow requests must not refill it mid-flood
    lobby_.bucket = Bucket(rate=0.01, burst=JOIN_BURST)
    statuses = [join(port, {"name": f"op{i}"})[0] for i in range(int(JOIN_BURST) + 30)]
    assert statuses.count(429) >= 20 and set(statuses) == {429, 503}
    status, answer = join(port, {"name": "ana"})
    assert status == 429 and "too many join requests" in one_line(answer)


def test_the_most_wanted_task_comes_first_and_a_complete_campaign_takes_no_one(lobby):
    lobby_, port = lobby
    assert lobby_.next_task().name == "stack"  # 3 wanted against 2; ties would go in file order
    lobby_.campaign = lobby_.campaign.__class__(**{**lobby_.campaign.__dict__, "tasks": ()})
    status, answer = join(port, {"name": "ana"})
    assert status == 410 and "all the episodes" in one_line(answer)


def test_an_invite_admits_its_operator_only(tmp_path):
    path = tmp_path / "c.toml"
    path.write_text('name = "c"\nout = "o"\noperators = ["ana", "bo"]\n[[task]]\nscene = "lift"\nepisodes = 1\n')
    campaign = load_campaign(path)
    tokens = issue_invites(campaign.out, campaign.operators)
    lobby = Lobby(campaign, "127.0.0.1", ADMIN, JOIN)
    lobby.paused = True  # an admitted join then stops at "paused", before a session starts
    server = start_lobby(lobby, 0)
    port = server.server_address[1]
    try:
        assert join(port, {"name": "ana"})[0] == 403  # a named campaign has no open join link
        status, answer = join(port, {"name": "bo"}, token=tokens["ana"])
        assert status == 403 and "another operator" in one_line(answer)
        assert join(port, {}, token=tokens["ana"])[0] == 503  # the invite names its operator
        assert join(port, {"name": "ana"}, token=tokens["ana"])[0] == 503
        assert ask(port, "GET", f"/join?token={tokens['bo']}")[0] == 200
    finally:
        server.shutdown()
        server.server_close()
