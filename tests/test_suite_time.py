"""The quick suite reports its own time and fails over its budget (tests/suite_time.py), shown on a tiny suite.

The tiny suite is three trivial tests run by a real pytest in a fresh process, with a conftest that marks
two of them unit and one e2e, as tests/conftest.py does, and registers the same clock.
"""

from __future__ import annotations

import os
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
TESTS = "def test_one():\n    assert 1\n\n\ndef test_two():\n    assert 2\n\n\ndef test_slow():\n    assert 3\n"
INI = "[pytest]\ntestpaths = suite\nmarkers =\n    unit: quick\n    browser: chromium\n    e2e: slow\n"


@pytest.fixture
def tiny(tmp_path) -> Path:
    (tmp_path / "suite").mkdir()
    (tmp_path / "suite" / "test_tiny.py").write_text(TESTS)
    (tmp_path / "conftest.py").write_text(CONFTEST)
    (tmp_path / "pytest.ini").write_text(INI)
    return tmp_path


def pytest_run(folder: Path, *args: str, budget: str | None = None) -> subprocess.CompletedProcess:
    env = {k: v for k, v in os.environ.items() if k != "TELEOP_UNIT_BUDGET"}
    if budget is not None:
        env["TELEOP_UNIT_BUDGET"] = budget
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", *args], cwd=folder, env=env,
                          capture_output=True, text=True, timeout=60)


def test_the_unit_suite_prints_its_wall_time_and_fails_over_its_budget(tiny):
    over = pytest_run(tiny, "-m", "unit", budget="0")
    assert over.returncode == 1, over.stdout + over.stderr
    assert "2 passed" in over.stdout and "unit suite: 2 tests in " in over.stdout
    assert "over TELEOP_UNIT_BUDGET=0 s" in over.stdout


@pytest.mark.e2e  # four more pytest processes: a second or two
def test_within_budget_it_passes_a_whole_run_sums_each_marker_and_a_narrowed_one_makes_no_suite_figure(tiny):
    bad = pytest_run(tiny, "-m", "unit", budget="two minutes")
    assert bad.returncode == 4 and "TELEOP_UNIT_BUDGET='two minutes': expected seconds" in bad.stderr
    within = pytest_run(tiny, "-m", "unit", budget="600")
    assert within.returncode == 0, within.stdout + within.stderr
    assert "unit suite: 2 tests in " in within.stdout and "FAILED" not in within.stdout
    whole = pytest_run(tiny, budget="0")  # unit tests summed: a few milliseconds, still over a budget of 0
    assert whole.returncode == 1, whole.stdout + whole.stderr
    assert "unit: 2 tests, " in whole.stdout and "e2e: 1 tests, " in whole.stdout and "unit suite:" not in whole.stdout
    narrowed = pytest_run(tiny, "-m", "unit", "-k", "one", budget="0")  # not the whole suite: no figure, no budget
    assert narrowed.returncode == 0, narrowed.stdout + narrowed.stderr
    assert "unit: 1 tests, " in narrowed.stdout and "unit suite:" not in narrowed.stdout
