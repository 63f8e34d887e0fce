"""Issue 49, item 4 in-process: the admin page's successful episodes per hour come from each episode's
recorded start time (EpisodeMeta.start_time), per operator and per task, read once per file (the ledger's
cache), with the file's modification time for a file that has no start time.
"""

from __future__ import annotations

import time
from pathlib import Path

import pytest

from devices.script import ScriptDevice
from replay.episode import load_episode
from teleop.campaign.ledger import HOUR_S, TaskCount, count_task, hourly_successes, started_at
from teleop.control.loop import run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session
from tests.support import ROOT

pytestmark = pytest.mark.unit


def record(folder: Path, operator: str, seed: int, succeed: bool = True) -> Path:
    """A real episode of the lift task by `operator`: the pick script to the end (a success), or 5 ticks of it."""
    session = Session("lift", robot="panda", seed=seed)
    Recorder(session, folder, verify="off", provenance={"operator": operator, "campaign": "trial", "session": f"s-{operator}"})
    script = ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")
    script.start()
    result = run_episode(session, [script], max_steps=None if succeed else 5)
    assert result.success == succeed
    return result.files[0]


def test_counts_carry_each_success_start_time_and_operator(tmp_path: Path):
    before = time.time()
    files = [record(tmp_path / "lift", "ana", 0), record(tmp_path / "lift", "bo", 1), record(tmp_path / "lift", "ana", 2, succeed=False)]
    count = count_task(tmp_path, "lift", settle=False)
    assert (count.episodes, count.successes) == (3, 2)
    assert sorted(op for _, op in count.success_times) == ["ana", "bo"]
    starts = [load_episode(f).meta.start_time for f in files[:2]]
    assert sorted(t for t, _ in count.success_times) == sorted(started_at(s, 0.0) for s in starts)
    assert all(before - 1 <= t <= time.time() for t, _ in count.success_times)
    timeline = hourly_successes({"lift": count})
    assert sum(timeline["campaign"]) == 2 and sum(timeline["tasks"]["lift"]) == 2
    assert {name: sum(v) for name, v in timeline["operators"].items()} == {"ana": 1, "bo": 1}


def test_hours_are_binned_from_the_first_success_to_now():
    now = 1_800_000_000.0  # Unix time, s
    hour = int(now // HOUR_S) * HOUR_S
    lift = TaskCount(success_times=[(hour - 3 * HOUR_S + 10, "ana"), (hour - 3 * HOUR_S + 20, "bo"), (hour + 5, "ana")])
    stack = TaskCount(success_times=[(hour - HOUR_S, None)])  # a success with no operator: the campaign's and its task's
    timeline = hourly_successes({"lift": lift, "stack": stack}, now=now)
    assert timeline["start"] == hour - 3 * HOUR_S and timeline["hour_s"] == HOUR_S
    assert timeline["campaign"] == [2, 0, 1, 1]
    assert timeline["operators"] == {"ana": [1, 0, 0, 1], "bo": [1, 0, 0, 0]}
    assert timeline["tasks"] == {"lift": [2, 0, 0, 1], "stack": [0, 0, 1, 0]}
    short = hourly_successes({"lift": lift}, now=now, max_hours=2)  # the span is capped: older hours drop out
    assert short["campaign"] == [0, 1] and short["start"] == hour - HOUR_S
    empty = hourly_successes({"lift": TaskCount()}, now=now)
    assert empty["campaign"] == [0] and empty["operators"] == {}


def test_a_start_time_without_a_zone_or_unreadable_falls_back_to_the_file_time():
    assert started_at("2026-11-27T12:00:00+00:00", 5.0) == pytest.approx(1795780800.0)
    assert started_at("2026-11-27T12:00:00", 5.0) == 5.0
    assert started_at("", 5.0) == 5.0 and started_at("yesterday", 5.0) == 5.0
