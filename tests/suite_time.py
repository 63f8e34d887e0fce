"""The suite's own clock: every run says how long each marker's tests took, so docs/install.md's figures stay true.

`pytest -m unit` is the check a person runs before every commit and must stay under 2 minutes of wall time on
the project's 2-core machine; the whole suite (`./run.sh test`) should stay under 15. The tests run on several
pytest-xdist workers at once, so summed test seconds overstate the wait: the clock reports, for each marker,
its tests' summed seconds (setup, call and teardown) and its WALL time, read from the reports' start and stop
times (epoch seconds, one machine's clock for every worker):

- unit: from the session's start (collection included) to the end of the last unit test. The unit tests run
  first (`order_unit_first`), so this is how long a person waits for them, in a whole run as in `-m unit`.
- browser, e2e: from their first test's start to their last one's end (they share the workers with each other).

Wall seconds grow when the workers outnumber the cores; CPU seconds do not. Each report also carries the CPU
seconds its phase used (user + system, of the worker and of the processes it started and reaped: servers,
Chromium, `teleop` commands), so the run ends with each marker's CPU seconds and the tests that used the most:
on 2 cores, the whole run cannot take less wall time than half its CPU seconds. Processes no test reaps (Ray's
daemons, Chromium's GPU process) escape that count, so the run also says how busy the machine's CPUs were over
its wall time (/proc/stat): near 100 %, only less work makes the run shorter, not more workers.

With TELEOP_UNIT_BUDGET=S set, a run of the whole unit suite (no -k, no paths; `-m unit` or no -m) fails when
the unit wall time is over S seconds: the quick suite getting slow is a failure, not a surprise. With
TELEOP_SUITE_WARN=S set, a run whose wall time passes S seconds ends with a warning (not a failure).

The clock is registered in every process (tests/conftest.py): in an xdist worker it only orders the items and
tags each with its marker (a user property the report carries to the controller); the controller, or a
serial run, adds up and reports.
"""

from __future__ import annotations

import os
import resource
import time

import pytest

from tests.warm_cli import WARM

BUDGET_ENV = "TELEOP_UNIT_BUDGET"
WARN_ENV = "TELEOP_SUITE_WARN"
MARKERS = ("unit", "browser", "e2e")
PROPERTY = "teleop_marker"  # the user property naming a test's marker, carried by its reports
CPU_PROPERTY = "teleop_cpu_s"  # the user property with the CPU seconds of a report's phase
TOP_CPU = 15  # the tests listed by CPU seconds at the end


def machine_cpu() -> tuple[float, float] | None:
    """(busy, total) CPU seconds of the whole machine since boot, all cores, from /proc/stat (None elsewhere)."""
    try:
        with open("/proc/stat") as stat:
            fields = [float(v) for v in stat.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    if len(fields) < 5:
        return None
    ticks = os.sysconf("SC_CLK_TCK")
    idle = fields[3] + fields[4]  # idle + iowait
    total = sum(fields[:8])  # user nice system idle iowait irq softirq steal (guest time is inside user)
    return (total - idle) / ticks, total / ticks


def cpu_seconds() -> float:
    """User + system CPU seconds of this process, of its reaped children (and theirs) and of the commands its
    warm process forked for it (tests/warm_cli.py), so far."""
    own, children = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime + WARM.cpu_s


def seconds_from_env(name: str) -> float | None:
    """The seconds in environment variable `name`, None when unset; a usage error when not a number."""
    value = os.environ.get(name, "").strip()
    try:
        return float(value) if value else None
    except ValueError:
        raise pytest.UsageError(f"{name}={value!r}: expected seconds, e.g. 120") from None


def marker_of(item: pytest.Item) -> str:
    """The item's marker: the first of MARKERS it carries ("" when none)."""
    return next((m for m in MARKERS if item.get_closest_marker(m)), "")


def order_unit_first(items: list[pytest.Item]) -> None:
    """Unit tests first, then browser, then e2e, each in collection order (a stable sort, in place).

    Unit first makes their wall time the wait for them. The browser tests are one xdist group, run on one worker
    (tests/conftest.py: one Chromium at a time), so they start next: the other workers take the e2e tests
    meanwhile, and the group does not trail behind them at the end.
    """
    rank = {"unit": 0, "browser": 1, "e2e": 2}
    items.sort(key=lambda item: rank.get(marker_of(item), 3))


class MarkerTime:
    """One marker's tests: their count, summed seconds and the span of their reports (epoch seconds)."""

    def __init__(self) -> None:
        self.tests: set[str] = set()
        self.seconds = 0.0
        self.cpu_s = 0.0
        self.first_start = float("inf")
        self.last_stop = 0.0

    def add(self, report: pytest.TestReport, cpu_s: float) -> None:
        self.tests.add(report.nodeid)
        self.seconds += report.duration
        self.cpu_s += cpu_s
        self.first_start = min(self.first_start, report.start)
        self.last_stop = max(self.last_stop, report.stop)


class SuiteClock:
    """A pytest plugin (conftest registers it): seconds and wall time by marker, the unit budget, the run's warning."""

    def __init__(self, config: pytest.Config) -> None:
        self.config = config
        self.is_worker = hasattr(config, "workerinput")  # an xdist worker: it orders and tags, the controller counts
        self.started = time.time()
        self.machine_at_start = machine_cpu()
        self.machine_busy = ""  # "92 % (3,170 of 3,445 core-seconds)": how busy the CPUs were over the run
        self.wall_s = 0.0
        self.times = {m: MarkerTime() for m in MARKERS}
        self.marker_by_nodeid: dict[str, str] = {}
        self.cpu_by_test: dict[str, float] = {}
        self.phase_cpu0 = 0.0  # cpu_seconds() when the running phase began (in the process running the tests)
        self.over_budget = ""
        self.over_warn = ""
        self.budget_s = seconds_from_env(BUDGET_ENV)
        self.warn_s = seconds_from_env(WARN_ENV)

    def whole_unit_suite(self) -> bool:
        """Every unit test selected: no -k, the configured test paths, and `-m unit` or no -m."""
        option = self.config.option
        return (option.markexpr or "").strip() in ("", "unit") and not (option.keyword or "").strip() \
            and self.config.args_source == pytest.Config.ArgsSource.TESTPATHS

    def unit_wall_s(self) -> float:
        """Seconds from the session's start to the end of the last unit test (0 when none ran)."""
        unit = self.times["unit"]
        return max(0.0, unit.last_stop - self.started) if unit.tests else 0.0

    @pytest.hookimpl(tryfirst=True)
    def pytest_sessionstart(self, session: pytest.Session) -> None:
        self.started = time.time()
        self.machine_at_start = machine_cpu()

    @pytest.hookimpl(trylast=True)
    def pytest_collection_modifyitems(self, items: list[pytest.Item]) -> None:
        """After the markers are given (conftest): unit tests first, and each test tagged with its marker."""
        order_unit_first(items)
        for item in items:
            if marker := marker_of(item):
                item.user_properties.append((PROPERTY, marker))

    def pytest_collection_finish(self, session: pytest.Session) -> None:
        self.marker_by_nodeid = {item.nodeid: marker_of(item) for item in session.items}

    @pytest.hookimpl(tryfirst=True)
    def _phase_starts(self, item: pytest.Item) -> None:
        """Before a test's setup, call or teardown runs: the CPU seconds its report will count from."""
        self.phase_cpu0 = cpu_seconds()

    pytest_runtest_setup = pytest_runtest_call = pytest_runtest_teardown = _phase_starts

    @pytest.hookimpl(hookwrapper=True)
    def pytest_runtest_makereport(self, item: pytest.Item, call: pytest.CallInfo):
        report = (yield).get_result()
        report.user_properties = [*report.user_properties, (CPU_PROPERTY, round(cpu_seconds() - self.phase_cpu0, 3))]

    def pytest_runtest_logreport(self, report: pytest.TestReport) -> None:
        if self.is_worker:
            return
        properties = dict(report.user_properties)
        cpu = float(properties.get(CPU_PROPERTY, 0.0))
        self.cpu_by_test[report.nodeid] = self.cpu_by_test.get(report.nodeid, 0.0) + cpu
        marker = properties.get(PROPERTY) or self.marker_by_nodeid.get(report.nodeid)
        if marker in self.times:
            self.times[marker].add(report, cpu)

    def pytest_sessionfinish(self, session: pytest.Session) -> None:
        if self.is_worker:
            return
        self.wall_s = time.time() - self.started
        end = machine_cpu()
        if end is not None and self.machine_at_start is not None and end[1] > self.machine_at_start[1]:
            busy, total = end[0] - self.machine_at_start[0], end[1] - self.machine_at_start[1]
            self.machine_busy = f"{100 * busy / total:.0f} % ({busy:,.0f} of {total:,.0f} core-seconds)"
        unit_wall = self.unit_wall_s()
        if self.budget_s is not None and self.times["unit"].tests and self.whole_unit_suite() and unit_wall > self.budget_s:
            self.over_budget = f"the unit tests took {unit_wall:.0f} s of wall time, over {BUDGET_ENV}={self.budget_s:g} s"
            if session.exitstatus == pytest.ExitCode.OK:
                session.exitstatus = pytest.ExitCode.TESTS_FAILED
        if self.warn_s is not None and self.wall_s > self.warn_s:
            self.over_warn = f"the run took {self.wall_s:.0f} s of wall time, over {WARN_ENV}={self.warn_s:g} s"

    def pytest_terminal_summary(self, terminalreporter) -> None:
        if self.is_worker:
            return
        ran = [m for m in MARKERS if self.times[m].tests]
        if not ran:
            return
        write = terminalreporter.write_line
        workers = getattr(self.config.option, "numprocesses", None) or 0
        terminalreporter.section("test time by marker", sep="-")
        for marker in ran:
            t = self.times[marker]
            if marker == "unit":
                span = f"{self.unit_wall_s():.1f} s wall from the session's start"
            else:
                span = f"{t.last_stop - t.first_start:.1f} s wall, ending {t.last_stop - self.started:.1f} s into the run"
            write(f"{marker}: {len(t.tests)} tests, {t.seconds:.1f} s summed, {span}, {t.cpu_s:.1f} CPU s")
        write(f"whole run: {self.wall_s:.1f} s wall ({f'{workers} workers' if workers else 'one process'}), "
              f"{sum(t.cpu_s for t in self.times.values()):.1f} CPU s")
        if self.machine_busy:
            write(f"the machine's CPUs were busy {self.machine_busy} over the run, by any process")
        top = sorted(self.cpu_by_test.items(), key=lambda kv: -kv[1])[:TOP_CPU]
        if top:
            write("most CPU seconds (setup, call and teardown):")
            for nodeid, cpu in top:
                write(f"  {cpu:7.1f} CPU s  {nodeid}")
        if self.times["unit"].tests and self.whole_unit_suite():
            write(f"unit suite: {len(self.times['unit'].tests)} tests in {self.unit_wall_s():.1f} s (wall, collection "
                  f"included; under 120 s on the project's 2-core machine)")
        if self.over_budget:
            write(f"FAILED: {self.over_budget}", red=True, bold=True)
        if self.over_warn:
            write(f"WARNING: {self.over_warn} (the whole suite should stay under 15 minutes)", yellow=True, bold=True)
