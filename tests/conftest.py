"""Shared test helpers: run the real CLI in a subprocess, write small files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


def run_cli(*args: str, timeout: float = 300, env: dict | None = None, cwd: Path | None = None) -> subprocess.CompletedProcess:
    """`teleop ARGS...` in a fresh process, as a user would run it."""
    full_env = {**os.environ, **(env or {})}
    full_env["PYTHONPATH"] = str(ROOT) + os.pathsep + full_env.get("PYTHONPATH", "")
    return subprocess.run(
        [sys.executable, "-m", "teleop", *args], capture_output=True, text=True, timeout=timeout, env=full_env, cwd=cwd or ROOT
    )


def run_json(*args: str, **kwargs) -> dict:
    """Run a CLI command that prints one JSON object, and parse it."""
    result = run_cli(*args, **kwargs)
    assert result.returncode == 0, f"exit {result.returncode}: {result.stderr[-2000:]}"
    return json.loads(result.stdout)


def write_script(path: Path, steps: list[dict]) -> Path:
    path.write_text(json.dumps({"steps": steps}))
    return path


def assert_one_line_error(result: subprocess.CompletedProcess, *needles: str) -> None:
    """Exit 2, a single line on stderr naming the problem, no traceback."""
    assert result.returncode == 2, f"exit {result.returncode}: {result.stderr}"
    lines = [line for line in result.stderr.strip().splitlines() if line.strip()]
    assert len(lines) == 1, f"expected one line, got: {result.stderr!r}"
    assert "Traceback" not in result.stderr
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"


@pytest.fixture
def tmp_script(tmp_path):
    def make(steps: list[dict], name: str = "script.json") -> Path:
        return write_script(tmp_path / name, steps)

    return make


@pytest.fixture(autouse=True)
def _sigint_handler_kept():
    """No test (and no library call it makes) leaves Ctrl-C handled differently from before it."""
    before = signal.getsignal(signal.SIGINT)
    yield
    after = signal.getsignal(signal.SIGINT)
    assert after == before, f"SIGINT handler changed from {before!r} to {after!r}"


@pytest.fixture(scope="module")
def browser():
    """A headless system Chromium (Playwright), one per test module."""
    from playwright import sync_api as playwright_api

    from tests import browser as headless

    with playwright_api.sync_playwright() as p:
        b = headless.launch(p)
        yield b
        b.close()
