"""Shared test helpers: run the real CLI in a subprocess, write small files."""

from __future__ import annotations

import json
import os
import re
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


# --- markers: `pytest -m unit` (quick, in-process), `-m browser` (headless Chromium), `-m e2e` -----------------
# e2e: whole jobs in real processes (export through LeRobot, lerobot-train, Ray, kill -9, a full disk, Xvfb).
E2E_FILES = {
    "test_disk_full.py", "test_disk_full_commands.py", "test_eval.py", "test_export.py", "test_export_parallel.py",
    "test_export_render.py", "test_export_resume.py", "test_export_stats.py", "test_generate.py",
    "test_generate_resume.py", "test_keyboard.py", "test_object_state.py", "test_packaging.py", "test_recorder_e2e.py",
    "test_robomimic.py", "test_takeover.py", "test_gym.py", "test_json_output.py", "test_cli_run.py", "test_train_eval.py",
}


def _uses_chromium(item: pytest.Item) -> bool:
    import inspect

    if "browser" in getattr(item, "fixturenames", ()):
        return True
    try:
        source = inspect.getsource(item.function)
    except (OSError, TypeError, AttributeError):
        return False
    return "headless.launch" in source or "sync_playwright" in source


# A test elsewhere is e2e too when it uses a real X server (the xvfb fixture), kills a process with SIGKILL,
# or runs `teleop export` (LeRobot), `generate` or `eval` in a subprocess; a slow one of another kind is marked
# `@pytest.mark.e2e` where it is defined.
E2E_FIXTURES = {"xvfb"}
E2E_SOURCE = re.compile(r"SIGKILL|\bkill -9\b|\(\s*[\"'](export|generate|eval)[\"']\s*,")


def _is_e2e(item: pytest.Item) -> bool:
    import inspect

    if item.get_closest_marker("e2e") or item.path.name in E2E_FILES or E2E_FIXTURES & set(getattr(item, "fixturenames", ())):
        return True
    try:
        return bool(E2E_SOURCE.search(inspect.getsource(item.function)))
    except (OSError, TypeError, AttributeError):
        return False


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test gets exactly one of the markers unit, browser, e2e (browser wins over e2e)."""
    for item in items:
        if item.get_closest_marker("browser") or _uses_chromium(item):
            item.add_marker(pytest.mark.browser)
        elif _is_e2e(item):
            item.add_marker(pytest.mark.e2e)
        else:
            item.add_marker(pytest.mark.unit)
