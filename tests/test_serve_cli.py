"""`teleop serve` as a command: user errors, absent devices, and Ctrl-C in the middle of an episode."""

from __future__ import annotations

import signal
import socket
import subprocess
import time
from pathlib import Path

import pytest

from tests import browser as headless
from tests.support import run_cli

REPO = Path(__file__).resolve().parents[1]


def serve(*args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return run_cli("serve", *args, timeout=timeout)


def test_port_in_use_is_a_usage_error():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = serve("--port", str(port))
    assert result.returncode == 2
    assert f"port {port}" in result.stderr and "in use" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


@pytest.mark.parametrize("args, words", [
    (("--device", "joystick"), "unknown device"),
    pytest.param(("--scene", "nowhere"), "unknown scene", marks=pytest.mark.e2e),  # a fresh `teleop` each: the first
    pytest.param(("--port", "0"), "--port", marks=pytest.mark.e2e),  # case runs in the quick suite, these in e2e
])
def test_bad_flags_are_one_line_errors(args, words):
    result = serve("--port", str(headless.free_port()), *args) if "--port" not in args else serve(*args)
    assert result.returncode == 2, result.stderr
    assert words in result.stderr and "Traceback" not in result.stderr


def test_ctrl_c_saves_the_episode_in_progress_as_incomplete(tmp_path):
    import playwright.sync_api as playwright_api  # the test extra installs it; Chromium comes from run.sh
    from replay import load_episode

    record = tmp_path / "episodes"
    server = headless.ServeProcess(["--record", str(record)], tmp_path)  # default devices: gizmo,keyboard,spacemouse
    try:
        status = server.status()
        assert "gizmo" in status["devices"]
        listed = " ".join(status["devices_not_started"]) + " ".join(status["devices"])
        assert "keyboard" in listed and "spacemouse" in listed  # absent devices are listed, not fatal
        with playwright_api.sync_playwright() as p:
            browser = headless.launch(p)
            page = headless.open_page(browser, server.url, size=(1100, 720))
            headless.click_button(page, "Record")
            server.wait_for(lambda s: s["recording"] and s["episode_steps"] > 15, what="recording")
            code = server.stop(signal.SIGINT)
            browser.close()
    finally:
        server.stop(signal.SIGKILL)
    log = server.log()
    assert code == 0, log
    (saved,) = sorted(record.glob("episode_*.mcap"))
    assert f"saved {saved}" in log and "incomplete" in log
    episode = load_episode(saved)
    assert episode.meta.complete is False and episode.steps > 15 and not episode.truncated


@pytest.mark.e2e  # starts a `teleop serve` server
def test_sigint_without_a_browser_exits_cleanly(tmp_path):
    server = headless.ServeProcess(["--device", "gizmo"], tmp_path)
    time.sleep(0.5)
    assert server.stop(signal.SIGINT) == 0
    assert "stopped" in server.log()
