"""Fixtures the tests share, and the markers each test gets; the helpers themselves are in tests/support.py."""

from __future__ import annotations

import ast
import contextlib
import functools
import os
import re
import select
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.register_assert_rewrite("tests.support")  # its asserts explain themselves like a test's

from tests.support import write_script  # noqa: E402 - after the rewrite is registered
from tests.warm_cli import WARM  # noqa: E402


@pytest.fixture
def tmp_script(tmp_path):
    def make(steps: list[dict], name: str = "script.json") -> Path:
        return write_script(tmp_path / name, steps)

    return make


@pytest.fixture(scope="module")
def xvfb() -> Iterator[str]:
    """A private X server; yields its DISPLAY string (":N")."""
    missing = [tool for tool in ("Xvfb", "xdotool") if not shutil.which(tool)]
    if missing:
        pytest.fail(f"keyboard tests need Debian packages xvfb and xdotool (missing: {', '.join(missing)})")
    read_end, write_end = os.pipe()
    proc = subprocess.Popen(
        ["Xvfb", "-displayfd", str(write_end), "-nolisten", "tcp", "-noreset", "-screen", "0", "320x240x24"],
        pass_fds=(write_end,),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    os.close(write_end)
    number = b""
    deadline = time.monotonic() + 15
    while not number.endswith(b"\n") and time.monotonic() < deadline:
        if select.select([read_end], [], [], 0.5)[0]:
            chunk = os.read(read_end, 16)
            if not chunk:
                break
            number += chunk
    os.close(read_end)
    if not number.strip():
        proc.kill()
        pytest.fail("Xvfb did not start")
    try:
        yield f":{number.decode().strip()}"
    finally:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@pytest.fixture(autouse=True)
def _sigint_handler_kept():
    """No test (and no library call it makes) leaves Ctrl-C handled differently from before it."""
    before = signal.getsignal(signal.SIGINT)
    yield
    after = signal.getsignal(signal.SIGINT)
    assert after == before, f"SIGINT handler changed from {before!r} to {after!r}"


def pytest_collection_finish(session: pytest.Session) -> None:
    """The environment `teleop` commands are forked with (tests/warm_cli.py): the test modules have set theirs
    (HF_HUB_OFFLINE) and no test has run."""
    WARM.settle_environment()


@pytest.hookimpl(trylast=True)
def pytest_runtest_teardown(item: pytest.Item) -> None:
    """No test leaves the environment changed for the next (tests/warm_cli.py: restore_environment)."""
    WARM.restore_environment()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item: pytest.Item) -> None:
    """Before any fixture of the test (a module's too): a unit test's `teleop` commands run in real interpreters,
    since starting the warm process (tests/warm_cli.py: LeRobot's imports, seconds of CPU per worker) would cost
    `pytest -m unit` more than it saves it; every other test's are forked from the warm process."""
    WARM.wanted = item.get_closest_marker("unit") is None


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


@functools.cache
def _source_of(function) -> str:
    """A test function's source ("" when there is none): read once for all its parametrized items."""
    import inspect

    try:
        return inspect.getsource(function)
    except (OSError, TypeError):
        return ""


def _uses_chromium(item: pytest.Item) -> bool:
    if "browser" in getattr(item, "fixturenames", ()):
        return True
    source = _source_of(getattr(item, "function", None))
    return "headless.launch" in source or "sync_playwright" in source


# A test elsewhere is e2e too when it uses a real X server (the xvfb fixture), kills a process with SIGKILL,
# or runs `teleop export` (LeRobot), `generate` or `eval` in a subprocess; a slow one of another kind is marked
# `@pytest.mark.e2e` where it is defined.
E2E_FIXTURES = {"xvfb"}
E2E_SOURCE = re.compile(r"SIGKILL|\bkill -9\b|\(\s*[\"'](export|generate|eval)[\"']\s*,")


def _is_e2e(item: pytest.Item) -> bool:
    if item.get_closest_marker("e2e") or item.path.name in E2E_FILES or E2E_FIXTURES & set(getattr(item, "fixturenames", ())):
        return True
    return bool(E2E_SOURCE.search(_source_of(getattr(item, "function", None))))


# --- parallel runs (pytest-xdist, `--dist loadgroup`: run.sh) ----------------------------------------------------
# A module-scoped fixture is set up once per worker that runs a test using it: a served session, a Chromium, a
# recorded-and-exported dataset would be made again on every worker. So the tests of a file that use one of its
# module-scoped fixtures (or conftest's `browser`, `xvfb`) run on one worker, as one xdist group per file (its unit
# tests a group of their own: they run first and never wait behind its slow ones); every other test goes to
# whichever worker is free.
CONFTEST_MODULE_FIXTURES = frozenset({"browser", "xvfb"})


@functools.cache
def module_scoped_fixtures(path: Path) -> frozenset[str]:
    """Names of the fixtures `path` defines with a scope wider than a function (module, class, package, session)."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.FunctionDef):
            continue
        for decorator in node.decorator_list:
            scope = next((k.value for k in getattr(decorator, "keywords", ()) if k.arg == "scope"), None)
            if isinstance(scope, ast.Constant) and scope.value != "function":
                names.add(node.name)
    return frozenset(names)


# The browser tests are one group of their own, "browser", with the tests of their files that share a fixture with
# them: one Chromium at a time. Run last, three at once (each drawing its scene with software WebGL on a 2-core
# machine), they starved each other's pages: in CI a replay page lagged its server past the episode's end, and
# an annotate page lost its listing for 30 s. tests/suite_time.py starts the group right after the unit tests,
# so it runs beside the e2e tests instead of after them.
BROWSER_GROUP = "browser"


def xdist_group_of(item: pytest.Item, marker: str, browser_files: set[Path] = frozenset()) -> str | None:
    """The xdist group of a test: "browser" for a browser test, and for a non-unit test of a file with browser
    tests that shares a module-scoped fixture; otherwise, for a test that uses a module-scoped fixture, its
    file (and "-unit" for a unit test); else None (any free worker)."""
    if marker == "browser":
        return BROWSER_GROUP
    shared = (module_scoped_fixtures(item.path) | CONFTEST_MODULE_FIXTURES) & set(getattr(item, "fixturenames", ()))
    if not shared:
        return None
    if marker == "unit":
        return f"{item.path.stem}-unit"
    return BROWSER_GROUP if item.path in browser_files else item.path.stem


@pytest.hookimpl(tryfirst=True)  # before xdist reads the groups and tests/suite_time.py orders by marker
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Every test gets exactly one of the markers unit, browser, e2e (browser wins over e2e), and its xdist group."""
    markers = {}
    for item in items:
        if item.get_closest_marker("browser") or _uses_chromium(item):
            markers[item] = "browser"
        elif _is_e2e(item):
            markers[item] = "e2e"
        else:
            markers[item] = "unit"
        item.add_marker(getattr(pytest.mark, markers[item]))
    browser_files = {item.path for item, marker in markers.items() if marker == "browser"}
    for item, marker in markers.items():
        if (group := xdist_group_of(item, marker, browser_files)) and not item.get_closest_marker("xdist_group"):
            item.add_marker(pytest.mark.xdist_group(group))


def pytest_ignore_collect(collection_path: Path, config: pytest.Config) -> bool | None:
    """`pytest -m unit` leaves the whole-file e2e modules unimported (their LeRobot and export imports cost seconds
    of the quick suite's time): every test in them is e2e or browser, so the selection is the same."""
    if (config.option.markexpr or "").strip() != "unit" or not collection_path.name.startswith("test_") \
            or collection_path.suffix != ".py":
        return None
    if collection_path.name in E2E_FILES or "\npytestmark = pytest.mark.e2e" in collection_path.read_text():
        return True
    return None


def pytest_configure(config: pytest.Config) -> None:
    """The suite's clock (tests/suite_time.py: wall time by marker, the unit budget), and Ray kept to this process.

    Ray's `ray.init()` joins the instance named in its temp dir's `ray_current_cluster` (which a local test
    cluster writes) instead of starting its own: with tests in parallel, one worker's Ray would be another's.
    Each pytest process that runs tests (an xdist worker, or a run without workers) gets a Ray temp dir of its
    own (short: Ray's socket paths must fit 107 bytes); xdist's controller sets none, which its workers would inherit.
    """
    from tests.suite_time import SuiteClock

    config.pluginmanager.register(SuiteClock(config), "teleop-suite-clock")
    WARM.say = functools.partial(_say_past_capture, config)
    runs_tests = hasattr(config, "workerinput") or not getattr(config.option, "numprocesses", None)
    if runs_tests and "RAY_TMPDIR" not in os.environ:
        os.environ["RAY_TMPDIR"] = config.stash[RAY_TMPDIR] = tempfile.mkdtemp(prefix="ray-", dir="/tmp")


RAY_TMPDIR = pytest.StashKey[str]()


def _say_past_capture(config: pytest.Config, line: str) -> None:
    """One line on the test run's stderr even from inside a test (pytest captures its output): the warm process's."""
    capture = config.pluginmanager.getplugin("capturemanager")
    with capture.global_and_fixture_disabled() if capture is not None else contextlib.nullcontext():
        print(line, file=sys.stderr, flush=True)


def pytest_unconfigure(config: pytest.Config) -> None:
    """The Ray temp dir this process made, removed with what Ray left in it (logs, sockets of stopped instances)."""
    WARM.close()
    if path := config.stash.get(RAY_TMPDIR, None):
        os.environ.pop("RAY_TMPDIR", None)
        shutil.rmtree(path, ignore_errors=True)
