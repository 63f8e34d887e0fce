"""Remote sessions need the token: the page, its websocket and the input channel refuse a request without it.

The served session listens on 0.0.0.0 (not loopback, so a token is required
and a random one is printed) and is reached through 127.0.0.1. The browser
part uses the system's headless Chromium through Playwright.
"""

from __future__ import annotations

import asyncio
import re
import time
import urllib.error
import urllib.request

import numpy as np
import pytest
import viser
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus
from websockets.http11 import Request
from websockets.datastructures import Headers

from teleop.errors import UsageError
from teleop.web.shared.access import TOKEN_ENV, TOKEN_PATTERN, Gate, resolve_token, same_origin, url_with_token
from teleop.web.viser_internals.serving_hooks import with_head_script
from tests import browser as headless
from tests.support import assert_one_line_error, run_cli

PAGE_SIZE = (1100, 720)
VISER_PROTOCOL = f"viser-v{viser.__version__}"


# -- the rules, without a server ------------------------------------------------
def test_loopback_is_open_unless_a_token_is_given():
    assert resolve_token("127.0.0.1", environ={}) is None
    assert resolve_token("localhost", environ={}) is None
    assert resolve_token("127.0.0.1", "my-secret-1", environ={}) == "my-secret-1"
    assert resolve_token("127.0.0.1", environ={TOKEN_ENV: "from-the-env"}) == "from-the-env"


def test_other_hosts_get_a_random_token_or_the_given_one():
    first, second = resolve_token("0.0.0.0", environ={}), resolve_token("0.0.0.0", environ={})
    assert first and second and first != second
    assert TOKEN_PATTERN.fullmatch(first) and len(first) >= 20
    assert resolve_token("0.0.0.0", "given-token", environ={TOKEN_ENV: "env-token-1"}) == "given-token"
    assert resolve_token("0.0.0.0", environ={TOKEN_ENV: "env-token-1"}) == "env-token-1"
    assert resolve_token("0.0.0.0", no_token=True, environ={TOKEN_ENV: "env-token-1"}) is None


@pytest.mark.parametrize("token, no_token, env, words", [
    ("abcdefgh", True, {}, "contradict"),
    ("short", False, {}, "--token"),
    ("has space in it", False, {}, "--token"),
    (None, False, {TOKEN_ENV: "bad/token/x"}, TOKEN_ENV),
])
def test_bad_tokens_and_combinations_are_usage_errors(token, no_token, env, words):
    with pytest.raises(UsageError, match=re.escape(words)):
        resolve_token("0.0.0.0", token, no_token, environ=env)


def _request(path: str, **headers: str) -> Request:
    return Request(path, Headers(**headers))


def test_the_gate_reads_the_token_from_the_query_or_the_port_s_cookie():
    gate = Gate("right-token", 8123)
    assert gate.allows(_request("/?token=right-token"))
    assert gate.allows(_request("/", Cookie="x=1; teleop_token_8123=right-token"))
    assert not gate.allows(_request("/"))
    assert not gate.allows(_request("/?token=wrong-token"))
    assert not gate.allows(_request("/", Cookie="teleop_token_8124=right-token"))  # another session's cookie
    assert gate.wants_cookie(_request("/?token=right-token")) and not gate.wants_cookie(_request("/"))
    assert "HttpOnly" in gate.set_cookie() and "SameSite=Strict" in gate.set_cookie()
    assert Gate(None, 8123).allows(_request("/"))
    assert url_with_token("http://127.0.0.1:8080", "abc-def-gh") == "http://127.0.0.1:8080/?token=abc-def-gh"
    assert url_with_token("http://127.0.0.1:8080", None) == "http://127.0.0.1:8080"
    # a page of its own keeps its path as served (the server answers `/phone`, not `/phone/`)
    assert url_with_token("http://127.0.0.1:8080/phone", "abc-def-gh") == "http://127.0.0.1:8080/phone?token=abc-def-gh"


def test_cross_origin_pages_are_told_apart():
    assert same_origin(_request("/teleop/input", Host="10.0.0.5:8080", Origin="http://10.0.0.5:8080"))
    assert not same_origin(_request("/teleop/input", Host="10.0.0.5:8080", Origin="https://evil.example"))
    assert same_origin(_request("/teleop/input", Host="10.0.0.5:8080"))  # a script, not a page


@pytest.mark.parametrize("args, env, words", [
    (("--token", "abcdefgh", "--no-token"), {}, "contradict"),
    pytest.param(("--token", "abc"), {}, "--token", marks=pytest.mark.e2e),  # a fresh `teleop` each: the first case
    pytest.param((), {TOKEN_ENV: "not a token"}, TOKEN_ENV, marks=pytest.mark.e2e),  # runs in the quick suite
])
def test_serve_rejects_bad_token_flags_in_one_line(args, env, words):
    result = run_cli("serve", "--port", str(headless.free_port()), *args, env=env, timeout=120)
    assert_one_line_error(result, words)


# -- a served session on 0.0.0.0 ------------------------------------------------
@pytest.fixture(scope="module")
def server(tmp_path_factory):
    proc = headless.ServeProcess(["--host", "0.0.0.0", "--device", "gizmo,keyboard"], tmp_path_factory.mktemp("serve"),
                                 env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})  # keys from the page only
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def token(server) -> str:
    match = re.search(rf"open http://127\.0\.0\.1:{server.port}/\?token=([A-Za-z0-9._~-]+) in a browser", server.log())
    assert match, server.log()
    return match.group(1)


def _get(url: str, **headers: str) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


@pytest.mark.e2e  # this module's `teleop serve` server on 0.0.0.0
def test_the_printed_url_carries_a_random_token_and_the_status_says_one_is_needed(server, token):
    assert TOKEN_PATTERN.fullmatch(token) and len(token) >= 20
    assert server.status()["token_required"] is True
    assert "warning" not in server.log()  # a token, so nothing to warn about


@pytest.mark.e2e  # this module's `teleop serve` server on 0.0.0.0
def test_http_without_the_token_is_403_and_with_it_200(server, token):
    status, _, body = _get(server.url + "/")
    assert status == 403 and b"token" in body
    assert _get(server.url + "/?token=" + token[:-1] + "x")[0] == 403
    status, headers, body = _get(server.url + "/?token=" + token)
    assert status == 200 and b"<html" in body.lower()
    assert f"teleop_token_{server.port}={token}" in headers["Set-Cookie"]
    assert _get(server.url + "/", Cookie=f"teleop_token_{server.port}={token}")[0] == 200
    assert _get(server.url + "/", Cookie=f"teleop_token_{server.port}=nope-nope-nope")[0] == 403


async def _ws_first_message(url: str, **kwargs) -> bytes | str:
    async with connect(url, subprotocols=[VISER_PROTOCOL], open_timeout=10, **kwargs) as ws:
        return await asyncio.wait_for(ws.recv(), 10)


@pytest.mark.e2e  # this module's `teleop serve` server on 0.0.0.0
def test_the_websocket_without_the_token_is_refused_and_with_it_accepted(server, token):
    ws_url = server.url.replace("http://", "ws://")
    evil = {"origin": "https://evil.example"}  # another site's page, even with the token (viser's websocket too)
    for url, kwargs in ((ws_url, {}), (ws_url + "/teleop/input", {}), (ws_url + "/?token=wrong-wrong-wrong", {}),
                        (ws_url + "/?token=" + token, evil), (ws_url + "/teleop/input?token=" + token, evil)):
        with pytest.raises(InvalidStatus) as refused:
            headless.run_async(_ws_first_message(url, **kwargs))
        assert refused.value.response.status_code == 403
    assert headless.run_async(_ws_first_message(ws_url + "/?token=" + token))  # viser's first message arrives
    cookie = {"additional_headers": {"Cookie": f"teleop_token_{server.port}={token}"}}
    assert headless.run_async(_ws_first_message(ws_url, **cookie))


def test_a_browser_without_the_token_sees_and_drives_nothing(server, browser):
    clients = server.status()["clients"]
    page = browser.new_page(viewport={"width": PAGE_SIZE[0], "height": PAGE_SIZE[1]})
    try:
        response = page.goto(server.url, timeout=60000)
        assert response is not None and response.status == 403
        time.sleep(3.0)
        assert page.locator("canvas").count() == 0
        assert server.status()["clients"] == clients
    finally:
        page.close()


def test_a_browser_with_the_token_draws_and_drags_and_its_cookie_lets_it_back(server, browser, token):
    page = headless.open_page(browser, server.url + "/?token=" + token, size=PAGE_SIZE)
    try:
        server.wait_for(lambda s: s["clients"] >= 1, what="the page to connect")
        # The page's key script got its input channel open too, past the token check.
        page.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60000)
        assert server.wait_for(lambda s: s["input"]["connections"] >= 1, what="the input channel")["input_dropped"] == 0
        time.sleep(2.0)  # the first meshes drawn (a drag that still grabs nothing is made again)
        headless.dismiss_toasts(page)
        before = server.status()
        target = np.array(before["target_pos"][0])
        after = headless.drag_gizmo_until(page, server.status, lambda s: np.linalg.norm(np.array(s["target_pos"][0]) - target) > 0.03)
        assert after["gizmo_drags"] > before["gizmo_drags"]
        # The same browser at the bare URL: the cookie set with the page brings the token.
        page.goto("about:blank")
        server.wait_for(lambda s: s["clients"] == 0, what="the page to go")
        page.goto(server.url, timeout=60000)
        page.wait_for_selector("canvas", timeout=60000)
        server.wait_for(lambda s: s["clients"] >= 1, what="the page to connect again by its cookie")
        page.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60000)
    finally:
        page.close()


@pytest.mark.e2e  # a `teleop serve` server of its own for each case
@pytest.mark.parametrize("args, needs_token", [
    (("--host", "0.0.0.0", "--no-token"), False),  # a trusted network: open, with a warning
    (("--token", "loopback-secret"), True),  # loopback, but a token was given: it is required
])
def test_no_token_opens_another_host_with_a_warning_and_a_given_token_guards_loopback(args, needs_token, tmp_path):
    proc = headless.ServeProcess(["--device", "gizmo", *args], tmp_path)
    try:
        log = proc.log()
        warnings = [line for line in log.splitlines() if line.startswith("warning:")]
        assert proc.status()["token_required"] is needs_token
        if needs_token:
            assert not warnings
            assert f"open {proc.url}/?token=loopback-secret in a browser" in log
            assert _get(proc.url + "/")[0] == 403 and _get(proc.url + "/?token=loopback-secret")[0] == 200
        else:
            assert len(warnings) == 1 and "--no-token" in warnings[0] and "anyone who can reach" in warnings[0]
            assert f"open {proc.url} in a browser" in log
            assert _get(proc.url + "/")[0] == 200
            assert headless.run_async(_ws_first_message(proc.url.replace("http://", "ws://")))
    finally:
        proc.stop()


def test_the_head_script_goes_first_in_viser_s_page_in_its_encoding():
    """viser answers its page gzipped or not; the script lands right after <head>, the length follows."""
    import gzip

    from websockets.http11 import Response

    page = b"<!doctype html><html><head><title>Viser</title></head><body></body></html>"
    script = b"<script>window.x = 1;</script>"
    cache: dict = {}
    for zipped in (False, True):
        body = gzip.compress(page) if zipped else page
        headers = Headers([("Content-Type", "text/html; charset=utf-8"), ("Content-Length", str(len(body))),
                           ("Content-Encoding", "gzip" if zipped else "identity")])
        out = with_head_script(Response(200, "OK", headers, body), script, cache)
        html = gzip.decompress(out.body) if zipped else out.body
        assert html == page.replace(b"<head>", b"<head>" + script)
        assert out.headers.get_all("Content-Length") == [str(len(out.body))]
        assert out.headers["Content-Encoding"] == ("gzip" if zipped else "identity")
    js = Response(200, "OK", Headers([("Content-Type", "application/javascript")]), b"<head>")
    assert with_head_script(js, script, cache).body == b"<head>"  # only the HTML page
