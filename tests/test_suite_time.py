"""The suite reports its own time, fails over its unit budget and warns over its whole-run figure
(tests/suite_time.py), shown on a tiny suite.

The tiny suite is three trivial tests run by a real pytest in a fresh process (serially, or on two xdist
workers as run.sh runs the real one), with a conftest that marks two of them unit and one e2e, as
tests/conftest.py does, and registers the same clock. The e2e test is defined first: the clock runs unit tests first.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support import ROOT

CONFTEST = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
import pytest
from tests.suite_time import SuiteClock


def pytest_collection_modifyitems(config, items):
    for item in items:
        item.add_marker(pytest.mark.e2e if "slow" in item.name else pytest.mark.unit)


def pytest_configure(config):
    config.pluginmanager.register(SuiteClock(config), "teleop-suite-clock")
"""
TESTS = ("import subprocess, sys\n\n\ndef test_slow():  # half a second of CPU in a child process\n"
         "    assert subprocess.run([sys.executable, '-c', 'sum(range(20_000_000))']).returncode == 0\n\n\n"
         "def test_one():\n    assert 1\n\n\ndef test_two():\n    assert 2\n")
INI = "[pytest]\ntestpaths = suite\nmarkers =\n    unit: quick\n    browser: chromium\n    e2e: slow\n"


@pytest.fixture
def tiny(tmp_path) -> Path:
    (tmp_path / "suite").mkdir()
    (tmp_path / "suite" / "test_tiny.py").write_text(TESTS)
    (tmp_path / "conftest.py").write_text(CONFTEST)
    (tmp_path / "pytest.ini").write_text(INI)
    return tmp_path


def pytest_run(folder: Path, *args: str, budget: str | None = None, warn: str | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k not in ("TELEOP_UNIT_BUDGET", "TELEOP_SUITE_WARN")}
    for name, value in (("TELEOP_UNIT_BUDGET", budget), ("TELEOP_SUITE_WARN", warn)):
        if value is not None:
            env[name] = value
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=120)


def marker_line(out: str, marker: str) -> tuple[int, float, float]:
    """(tests, summed s, wall s) from the clock's line for `marker`."""
    found = re.search(rf"^{marker}: (\d+) tests, ([\d.]+) s summed, ([\d.]+) s wall", out, re.M)
    assert found, out
    return int(found[1]), float(found[2]), float(found[3])


def cpu_of(out: str, marker: str) -> float:
    """The CPU seconds at the end of the clock's line for `marker`."""
    found = re.search(rf"^{marker}: .*, ([\d.]+) CPU s$", out, re.M)
    assert found, out
    return float(found[1])


def most_cpu(out: str) -> list[str]:
    """The test names under "most CPU seconds", in order."""
    return re.findall(r"^  +[\d.]+ CPU s  \S+::(\w+)$", out.split("most CPU seconds", 1)[-1], re.M)


def whole_wall(out: str) -> float:
    found = re.search(r"^whole run: ([\d.]+) s wall", out, re.M)
    assert found, out
    return float(found[1])


def test_the_unit_suite_prints_its_wall_time_and_fails_over_its_budget(tiny):
    over = pytest_run(tiny, "-m", "unit", budget="0")
    assert over.returncode == 1, over.stdout + over.stderr
    assert "2 passed" in over.stdout and "unit suite: 2 tests in " in over.stdout
    assert "over TELEOP_UNIT_BUDGET=0 s" in over.stdout


@pytest.mark.e2e  # five more pytest processes: a few seconds
def test_within_budget_it_passes_a_whole_run_times_each_marker_and_a_narrowed_one_has_no_budget(tiny):
    bad = pytest_run(tiny, "-m", "unit", budget="two minutes")
    assert bad.returncode == 4 and "TELEOP_UNIT_BUDGET='two minutes': expected seconds" in bad.stderr
    within = pytest_run(tiny, "-m", "unit", budget="600")
    assert within.returncode == 0, within.stdout + within.stderr
    assert "unit suite: 2 tests in " in within.stdout and "FAILED" not in within.stdout
    whole = pytest_run(tiny, "-v", budget="0")  # a whole run holds the whole unit suite: its wall time, over 0 s
    assert whole.returncode == 1, whole.stdout + whole.stderr
    assert "over TELEOP_UNIT_BUDGET=0 s" in whole.stdout and "unit suite: 2 tests in " in whole.stdout
    order = re.findall(r"::(test_\w+) PASSED", whole.stdout)
    assert order == ["test_one", "test_two", "test_slow"], whole.stdout  # unit tests first, though defined after
    (units, unit_sum, unit_wall), (e2es, _, e2e_wall) = marker_line(whole.stdout, "unit"), marker_line(whole.stdout, "e2e")
    assert (units, e2es) == (2, 1) and unit_sum <= unit_wall <= whole_wall(whole.stdout) and e2e_wall <= whole_wall(whole.stdout)
    # the child's CPU seconds are the e2e test's; the unit tests used next to none
    assert cpu_of(whole.stdout, "e2e") >= 0.2 > cpu_of(whole.stdout, "unit") and most_cpu(whole.stdout)[0] == "test_slow"
    narrowed = pytest_run(tiny, "-m", "unit", "-k", "one", budget="0")  # not the whole suite: no figure, no budget
    assert narrowed.returncode == 0, narrowed.stdout + narrowed.stderr
    assert marker_line(narrowed.stdout, "unit")[0] == 1 and "unit suite:" not in narrowed.stdout


@pytest.mark.e2e  # pytest on two xdist workers: a few seconds
def test_on_xdist_workers_the_controller_times_each_marker_fails_over_budget_and_warns_past_the_run_figure(tiny):
    over = pytest_run(tiny, "-n", "2", budget="0", warn="0")
    assert over.returncode == 1, over.stdout + over.stderr
    assert "3 passed" in over.stdout and "whole run: " in over.stdout and "(2 workers)" in over.stdout
    assert marker_line(over.stdout, "unit")[0] == 2 and marker_line(over.stdout, "e2e")[0] == 1  # the workers' reports, counted
    assert cpu_of(over.stdout, "e2e") >= 0.2 and most_cpu(over.stdout)[0] == "test_slow"  # CPU seconds, carried over too
    busy = re.search(r"^the machine's CPUs were busy (\d+) % \(([\d,]+) of ([\d,]+) core-seconds\)", over.stdout, re.M)
    assert busy and 0 <= int(busy[1]) <= 100, over.stdout
    cores_s = float(busy[3].replace(",", ""))  # every core's seconds over the run: about wall x cores
    assert 0.5 * whole_wall(over.stdout) * os.cpu_count() <= cores_s <= 1.5 * whole_wall(over.stdout) * os.cpu_count() + 2
    assert "over TELEOP_UNIT_BUDGET=0 s" in over.stdout and "WARNING: the run took" in over.stdout
    warned = pytest_run(tiny, "-n", "2", warn="0")  # the whole run's figure only warns
    assert warned.returncode == 0, warned.stdout + warned.stderr
    assert "over TELEOP_SUITE_WARN=0 s" in warned.stdout and "FAILED" not in warned.stdout
    quiet = pytest_run(tiny, "-n", "2", budget="600", warn="900")
    assert quiet.returncode == 0 and "WARNING" not in quiet.stdout and "FAILED" not in quiet.stdout, quiet.stdout
    bad = pytest_run(tiny, "-n", "2", warn="soon")
    assert bad.returncode == 4 and "TELEOP_SUITE_WARN='soon': expected seconds" in bad.stderr


GROUPED_CONFTEST = f"""
import sys
sys.path.insert(0, {str(ROOT)!r})
import pytest
from tests.conftest import xdist_group_of


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    for item in items:
        item.add_marker(pytest.mark.e2e)
        if group := xdist_group_of(item, "e2e"):
            item.add_marker(pytest.mark.xdist_group(group))
"""
GROUPED_TESTS = '''
import os
import time
import pytest


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    with open(os.environ["SETUPS_LOG"], "a") as log:
        log.write(f"{os.getpid()}\\n")
    time.sleep(0.5)
    return 1


@pytest.mark.parametrize("i", range(4))
def test_other(i):
    time.sleep(0.3)


def test_first(made):
    assert made


@pytest.mark.parametrize("i", range(4))
def test_more(i):
    time.sleep(0.3)


def test_second(made):
    assert made


def test_third(made):
    assert made
'''


@pytest.mark.e2e  # a pytest run on 3 xdist workers: four processes, seconds of the quick suite's time
def test_tests_sharing_a_module_fixture_run_on_one_worker_and_make_it_once(tmp_path):
    """run.sh's `--dist loadgroup` with tests/conftest.py's groups: a file's module-scoped fixture is made once, not
    once per worker (pytest 9.2 ignores the group xdist 3.8 writes into a test's id: pyproject pins pytest below it)."""
    (tmp_path / "suite").mkdir()
    (tmp_path / "suite" / "test_shared.py").write_text(GROUPED_TESTS)
    (tmp_path / "conftest.py").write_text(GROUPED_CONFTEST)
    (tmp_path / "pytest.ini").write_text(INI)
    log = tmp_path / "setups.log"
    env = {**os.environ, "SETUPS_LOG": str(log)}
    done = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "-n", "3", "--dist", "loadgroup"],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stdout + done.stderr
    assert "11 passed" in done.stdout
    assert len(log.read_text().split()) == 1, f"the module fixture was made on several workers: {log.read_text().split()}"


def test_browser_tests_are_one_group_with_the_tests_sharing_their_fixtures():
    """One Chromium at a time: every browser test is in the "browser" group, with the e2e tests of its file that
    share a module fixture with it (made once); a test sharing nothing goes to any free worker."""
    from types import SimpleNamespace

    from tests.conftest import BROWSER_GROUP, xdist_group_of

    replay = ROOT / "tests" / "test_web_replay.py"  # its `episode` fixture is module-scoped

    def test(*fixtures: str) -> SimpleNamespace:
        return SimpleNamespace(path=replay, fixturenames=list(fixtures))

    assert xdist_group_of(test("tmp_path"), "browser", {replay}) == BROWSER_GROUP == "browser"
    assert xdist_group_of(test("episode"), "e2e", {replay}) == "browser"
    assert xdist_group_of(test("episode"), "e2e", set()) == "test_web_replay"  # a file without browser tests
    assert xdist_group_of(test("tmp_path"), "e2e", {replay}) is None
    assert xdist_group_of(test("episode"), "unit", {replay}) == "test_web_replay-unit"
