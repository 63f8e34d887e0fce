"""The replay viewer (`teleop replay EP --serve`) behind the session's gate: token, cookie, Origin.

As tests/test_web_access.py does for `teleop serve`: a viewer on 0.0.0.0 (not
loopback, so a random token is printed) is reached through 127.0.0.1 with raw
HTTP, raw websockets and the system's headless Chromium (Playwright). The page
can write the episode's subtask file, so that must need the token too.
"""

from __future__ import annotations

import asyncio
import json
import re
import signal
import subprocess
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest
import viser
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus

from teleop.web.shared.access import TOKEN_ENV, TOKEN_PATTERN
from teleop.web.shared.net import exposure_warning, page_url, remote_hint
from tests import browser as headless
from tests.support import ROOT, assert_one_line_error, popen_cli, run_cli

VISER_PROTOCOL = f"viser-v{viser.__version__}"
SCRIPT = {"steps": [
    {"duration": 0.5, "to_body": "cube", "offset": [0, 0, 0.1], "gripper": "open"},
    {"duration": 0.3, "move": [0, 0, -0.05]},
]}


# -- the page's address, without a server ------------------------------------------
def test_the_page_url_brackets_ipv6_and_names_a_loopback_for_wildcards():
    assert page_url("127.0.0.1", 8080) == "http://127.0.0.1:8080"
    assert page_url("0.0.0.0", 8080) == "http://127.0.0.1:8080"
    assert page_url("", 8080) == "http://127.0.0.1:8080"
    assert page_url("::1", 8080) == "http://[::1]:8080"
    assert page_url("::", 8080) == "http://[::1]:8080"  # asyncio listens on IPv6 only for "::"
    assert page_url("fe80::1", 9000) == "http://[fe80::1]:9000"
    assert page_url("robot-box", 8080) == "http://robot-box:8080"
    assert remote_hint("127.0.0.1") is None and remote_hint("10.0.0.5") is None
    assert "127.0.0.1" in remote_hint("0.0.0.0") and "[::1]" in remote_hint("::")


def test_the_viewer_s_warning_says_what_it_exposes():
    from teleop.web.replay_page.viewer import VIEWER_REACH

    warning = exposure_warning("0.0.0.0", 8080, VIEWER_REACH)
    assert warning.startswith("warning: --no-token") and "subtask file" in warning and "\n" not in warning
    assert exposure_warning("::1", 8080, VIEWER_REACH) is None


# -- a recorded episode, and the viewer in a subprocess ------------------------------
@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("replay_access")
    script = work / "short.json"
    script.write_text(json.dumps(SCRIPT))
    result = run_cli("run", "--device", f"script:{script}", "--record", str(work / "eps"), "--json", timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    (path,) = sorted((work / "eps").glob("*.mcap"))
    return path


@pytest.mark.parametrize("args, env, words", [
    (("--serve", "--token", "abcdefgh", "--no-token"), {}, "contradict"),
    pytest.param(("--serve", "--token", "abc"), {}, "--token", marks=pytest.mark.e2e),  # a fresh `teleop` each: the
    pytest.param(("--serve",), {TOKEN_ENV: "not a token"}, TOKEN_ENV, marks=pytest.mark.e2e),  # first case runs in
    pytest.param(("--token", "abcdefgh"), {}, "--serve", marks=pytest.mark.e2e),  # the quick suite; the token is the viewer's
])
def test_replay_rejects_bad_token_flags_in_one_line(episode, args, env, words):
    result = run_cli("replay", str(episode), "--port", str(headless.free_port()), *args, env=env, timeout=120)
    assert_one_line_error(result, words)


class Viewer:
    """`python -m teleop replay EP --serve ...` in a subprocess, ready once it printed its URL."""

    def __init__(self, episode: Path, args: list[str], workdir: Path, env: dict | None = None) -> None:
        self.port = headless.free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log_file = workdir / f"replay-{self.port}.log"
        self._log = open(self.log_file, "w")
        self.proc = popen_cli(["replay", str(episode), "--serve", "--port", str(self.port), *args], self._log,
                              env=env, cwd=ROOT)
        deadline = time.monotonic() + 90
        while "open http" not in self.log():
            assert self.proc.poll() is None and time.monotonic() < deadline, self.log()
            time.sleep(0.2)

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_file.read_text()

    def stop(self) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self._log.close()
        return self.proc.returncode


@pytest.fixture(scope="module")
def viewer(episode, tmp_path_factory):
    proc = Viewer(episode, ["--host", "0.0.0.0"], tmp_path_factory.mktemp("viewer"), env={TOKEN_ENV: ""})
    yield proc
    assert proc.stop() == 0, proc.log()


@pytest.fixture(scope="module")
def token(viewer) -> str:
    match = re.search(rf"open http://127\.0\.0\.1:{viewer.port}/\?token=([A-Za-z0-9._~-]+) in a browser", viewer.log())
    assert match, viewer.log()
    return match.group(1)


def _get(url: str, **headers: str) -> tuple[int, dict, bytes]:
    try:
        with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


async def _ws_first_message(url: str, **kwargs) -> bytes | str:
    async with connect(url, subprotocols=[VISER_PROTOCOL], open_timeout=10, **kwargs) as ws:
        return await asyncio.wait_for(ws.recv(), 10)


@pytest.mark.e2e  # this module's `teleop replay --serve` viewer
def test_off_loopback_the_viewer_prints_a_random_token_and_warns_of_nothing(viewer, token):
    assert TOKEN_PATTERN.fullmatch(token) and len(token) >= 20
    assert "warning" not in viewer.log()
    assert "from another machine" in viewer.log()


@pytest.mark.e2e  # this module's `teleop replay --serve` viewer
def test_viewer_http_without_the_token_is_403_and_with_it_200(viewer, token):
    status, _, body = _get(viewer.url + "/")
    assert status == 403 and b"token" in body
    assert _get(viewer.url + "/?token=" + token[:-1] + "x")[0] == 403
    status, headers, body = _get(viewer.url + "/?token=" + token)
    assert status == 200 and b"<html" in body.lower()
    assert f"teleop_token_{viewer.port}={token}" in headers["Set-Cookie"] and "HttpOnly" in headers["Set-Cookie"]
    assert _get(viewer.url + "/", Cookie=f"teleop_token_{viewer.port}={token}")[0] == 200
    assert _get(viewer.url + "/", Cookie=f"teleop_token_{viewer.port}=nope-nope-nope")[0] == 403


@pytest.mark.e2e  # this module's `teleop replay --serve` viewer
def test_viewer_websocket_is_refused_without_the_token_or_from_another_site(viewer, token):
    ws_url = viewer.url.replace("http://", "ws://")
    refused = [
        (ws_url, {}),
        (ws_url + "/?token=wrong-wrong-wrong", {}),
        (ws_url + "/?token=" + token, {"origin": "https://evil.example"}),  # another site's page, even with it
    ]
    for url, kwargs in refused:
        with pytest.raises(InvalidStatus) as caught:
            headless.run_async(_ws_first_message(url, **kwargs))
        assert caught.value.response.status_code == 403, url
    assert headless.run_async(_ws_first_message(ws_url + "/?token=" + token))  # viser's first message arrives
    same_site = {"origin": viewer.url, "additional_headers": {"Cookie": f"teleop_token_{viewer.port}={token}"}}
    assert headless.run_async(_ws_first_message(ws_url, **same_site))


def test_a_browser_needs_the_token_to_see_the_episode_and_save_its_subtasks(viewer, token, episode, browser):
    sidecar = episode.with_name(episode.name + ".subtasks.json")
    page = browser.new_page(viewport={"width": 1000, "height": 700})
    try:
        response = page.goto(viewer.url, timeout=60000)
        assert response is not None and response.status == 403
        assert page.locator("canvas").count() == 0
    finally:
        page.close()
    assert not sidecar.exists()
    page = headless.open_page(browser, viewer.url + "/?token=" + token, size=(1000, 700))
    try:
        page.get_by_text(episode.name).first.wait_for(timeout=60000)
        page.get_by_text("Subtasks").first.wait_for(timeout=60_000)
        headless.click_button(page, "Save")
        page.wait_for_function("() => [...document.querySelectorAll('*')].some(e => /saved to /.test(e.textContent))",
                               timeout=30000, polling=100)
    finally:
        page.close()
    doc = json.loads(sidecar.read_text())
    assert doc["by"] == "human" and doc["subtasks"][0]["start"] == 0


@pytest.mark.e2e  # a `teleop replay --serve` viewer of its own for each case
@pytest.mark.parametrize("args, needs_token", [
    (("--host", "0.0.0.0", "--no-token"), False),  # a trusted network: open, with one warning line
    (("--token", "loopback-secret"), True),  # loopback, but a token was given: it is required
    ((), False),  # loopback, as before tokens existed
])
def test_no_token_warns_a_given_token_guards_loopback_and_plain_loopback_is_open(episode, tmp_path, args, needs_token):
    proc = Viewer(episode, list(args), tmp_path, env={TOKEN_ENV: ""})
    try:
        log = proc.log()
        warnings = [line for line in log.splitlines() if line.startswith("warning:")]
        if needs_token:
            assert f"open {proc.url}/?token=loopback-secret in a browser" in log
            assert _get(proc.url + "/")[0] == 403 and _get(proc.url + "/?token=loopback-secret")[0] == 200
        else:
            assert f"open {proc.url} in a browser" in log
            assert _get(proc.url + "/")[0] == 200
            assert headless.run_async(_ws_first_message(proc.url.replace("http://", "ws://")))
        if "--no-token" in args:
            assert len(warnings) == 1 and "--no-token" in warnings[0] and "subtask file" in warnings[0]
        else:
            assert not warnings
    finally:
        assert proc.stop() == 0, proc.log()
