"""The quick suite's own clock: every run says how long each marker's tests took, so docs/install.md's figure stays true.

`pytest -m unit` is the check a person runs before every commit and must stay under 2 minutes on the project's
2-core machine. A run of the whole suite (CI) prints the seconds its unit, browser and e2e tests took, summed
over setup, call and teardown; a run of the whole unit suite (`-m unit`, no paths, no -k) prints its wall time,
collection included. With TELEOP_UNIT_BUDGET=S set, the session fails when that figure is over S seconds: the
quick suite getting slow is a failure, not a surprise.
"""

from __future__ import annotations

import os
import time

import pytest

BUDGET_ENV = "TELEOP_UNIT_BUDGET"
MARKERS = ("unit", "browser", "e2e")


class SuiteClock:
    """A pytest plugin (conftest registers it): seconds and tests by marker, and the unit suite's figure."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.started = time.monotonic()
        self.wall_s = 0.0
        self.seconds = {m: 0.0 for m in MARKERS}
        self.tests: dict[str, set[str]] = {m: set() for m in MARKERS}
        self.marker_of: dict[str, str] = {}
        self.over_budget = ""
        budget = os.environ.get(BUDGET_ENV, "").strip()
        try:
            self.budget_s = float(budget) if budget else None
        except ValueError:
            raise pytest.UsageError(f"{BUDGET_ENV}={budget!r}: expected seconds, e.g. 120") from None

    def whole_unit_suite(self) -> bool:
        """`-m unit` over the configured test paths, nothing narrowed by -k: the figure docs/install.md quotes."""
        option = self.config.option
        return (option.markexpr or "").strip() == "unit" and not (option.keyword or "").strip() \
            and self.config.args_source == pytest.Config.ArgsSource.TESTPATHS

    def unit_figure(self) -> tuple[str, float] | None:
        """('wall', s) for a whole `-m unit` run, ('summed', s) for a run that also ran other markers."""
        if self.whole_unit_suite():
            return "wall", self.wall_s
        if self.tests["unit"] and (self.tests["browser"] or self.tests["e2e"]):
            return "summed", self.seconds["unit"]
        return None

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionstart(self, session: pytest.Session) -> None:
        self.started = time.monotonic()

    def pytest_collection_finish(self, session: pytest.Session) -> None:
        """Each selected test's marker (conftest gives every test exactly one)."""
        self.marker_of = {item.nodeid: next((m for m in MARKERS if item.get_closest_marker(m)), "") for item in session.items}

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if marker := self.marker_of.get(report.nodeid):
            self.seconds[marker] += report.duration
            self.tests[marker].add(report.nodeid)

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        self.wall_s = time.monotonic() - self.started
        figure = self.unit_figure()
        if self.budget_s is not None and figure is not None and figure[1] > self.budget_s:
            self.over_budget = f"the unit tests took {figure[1]:.0f} s ({figure[0]}), over {BUDGET_ENV}={self.budget_s:g} s"
            if session.exitstatus == pytest.ExitCode.OK:
                session.exitstatus = pytest.ExitCode.TESTS_FAILED

    def pytest_terminal_summary(self, terminalreporter) -> None:
        ran = [m for m in MARKERS if self.tests[m]]
        if not ran:
            return
        write = terminalreporter.write_line
        terminalreporter.section("test time by marker", sep="-")
        for marker in ran:
            write(f"{marker}: {len(self.tests[marker])} tests, {self.seconds[marker]:.1f} s summed")
        if self.whole_unit_suite():
            write(f"unit suite: {len(self.tests['unit'])} tests in {self.wall_s:.1f} s (wall, collection included; "
                  f"under 120 s on the project's 2-core machine)")
        if self.over_budget:
            write(f"FAILED: {self.over_budget}", red=True, bold=True)
