"""`teleop replay PATH --serve`: the recorded episode in the browser, with a timeline, play/pause and speed."""

from __future__ import annotations

import json
import re
import signal
import socket
import time
from pathlib import Path

import pytest

from tests import browser as headless
from tests.support import popen_cli, run_cli, run_json

REPO = Path(__file__).resolve().parents[1]
SCRIPT = {"steps": [
    {"duration": 0.8, "to_body": "cube", "offset": [0, 0, 0.1], "gripper": "open"},
    {"duration": 0.6, "move": [0, 0, -0.1]},
    {"duration": 0.4, "gripper": "close"},
    {"duration": 0.8, "move": [0, 0, 0.15]},
    {"duration": 40.0, "move": [-0.1, 0.1, 0]},  # long: a slow machine must not reach the end while the test pauses
]}


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("replay")
    script = work / "lift.json"
    script.write_text(json.dumps(SCRIPT))
    run_json("run", "--device", f"script:{script}", "--record", str(work / "eps"), "--json")
    (path,) = sorted((work / "eps").glob("*.mcap"))
    return path


@pytest.mark.e2e  # records an episode, then runs `teleop replay --serve`, each in a fresh process
def test_replay_serve_port_in_use(episode):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = run_cli("replay", str(episode), "--serve", "--port", str(port), timeout=60)
    assert result.returncode == 2 and f"port {port}" in result.stderr


def test_replay_in_the_browser_plays_and_scrubs(episode, tmp_path):
    import playwright.sync_api as playwright_api  # the test extra installs it; Chromium comes from run.sh
    port = headless.free_port()
    log = open(tmp_path / "replay.log", "w")
    proc = popen_cli(["replay", str(episode), "--serve", "--port", str(port)], log)
    stopped = False
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "open http" not in (tmp_path / "replay.log").read_text():
            assert proc.poll() is None, (tmp_path / "replay.log").read_text()
            time.sleep(0.2)
        with playwright_api.sync_playwright() as p:
            browser = headless.launch(p)
            page = headless.open_page(browser, f"http://127.0.0.1:{port}", size=(1100, 720))

            def shown_time() -> float:
                text = page.get_by_text(re.compile(r"^t = ")).first.text_content()
                return float(text.split()[2])

            page.get_by_text(episode.name).first.wait_for(timeout=60_000)
            assert page.get_by_text("Step").count() >= 1
            # headless Chromium draws WebGL in software: the viewer gives it the session's lighter view
            # (half resolution, asked for before viser starts; no shadows or environment light, from the server)
            assert "fixedDpr=0.5" in page.url, page.url
            lighter = time.monotonic() + 60
            while "draws WebGL without a GPU" not in (tmp_path / "replay.log").read_text():
                assert time.monotonic() < lighter, (tmp_path / "replay.log").read_text()
                time.sleep(0.2)
            assert shown_time() == 0.0
            # a quarter of real time: the server plays on while a loaded machine's page lags it, and the test must
            # pause well before the end (170 s away at 0.25x), whatever the page showed when it clicked
            headless.pick(page, "Speed", "0.25x")
            headless.click_button(page, "Play")
            page.get_by_role("button", name="Pause", exact=True).wait_for(timeout=60_000)
            moving = time.monotonic() + 15  # playing moves the timeline (the page may lag on a loaded machine)
            while time.monotonic() < moving and shown_time() <= 0.2:
                time.sleep(0.2)
            assert shown_time() > 0.2
            headless.click_button(page, "Pause")
            page.get_by_role("button", name="Play", exact=True).wait_for(timeout=60_000)
            # The page may lag the server on a loaded machine: wait for the clock to settle,
            # well before the episode's end (42.6 s of episode), then check that it stays put.
            paused, settle, still = shown_time(), time.monotonic() + 60, 0
            while time.monotonic() < settle and still < 2:  # unchanged over two seconds in a row: settled
                time.sleep(1.0)
                now = shown_time()
                still = still + 1 if now == paused else 0
                paused = now
            assert paused < 35.0, paused
            time.sleep(1.0)
            assert shown_time() == paused
            # scrub: type a step into the slider's number box
            box = page.locator("input.mantine-NumberInput-input:visible").first
            box.fill("10")
            box.press("Enter")
            page.wait_for_function("() => [...document.querySelectorAll('*')].some(e => e.textContent.trim().startsWith('t = 0.33'))",
                                   timeout=60_000)
            # the viewer stopped: its page says so across the top, as the session's does
            proc.send_signal(signal.SIGINT)
            stopped = True
            page.wait_for_function("() => document.getElementById('teleop-disconnected') !== null", timeout=60_000)
            assert page.locator("#teleop-disconnected").is_visible()
            browser.close()
    finally:
        if not stopped:
            proc.send_signal(signal.SIGINT)
        code = proc.wait(20)
        log.close()
    assert code == 0, (tmp_path / "replay.log").read_text()
