"""The page's camera picture: rendered from real snapshots by the real renderer, not redrawn while nothing moves,
and slower while the machine's CPUs are crowded."""

from __future__ import annotations

import time

import numpy as np

from devices.command import Command
from teleop.control.session import Session
from teleop.web.session_page.camera_view import CameraFeed
from teleop.web.shared.cpu_pressure import cpu_pressure
from teleop.web.session_page.panel import PanelDevice
from teleop.web.session_page.sim_thread import SimThread


def _wait(predicate, seconds: float = 20.0) -> None:
    deadline = time.monotonic() + seconds
    while not predicate():
        assert time.monotonic() < deadline, "timed out"
        time.sleep(0.01)


def test_an_idle_scene_is_not_redrawn_and_a_moved_one_is():
    session = Session(scene="lift", robot="panda", control_hz=30.0)
    panel = PanelDevice()
    sim = SimThread(session, [panel], log=lambda message: None)
    current = [sim.step_once()]  # the snapshot the feed sees: set by the test only after whole moves
    cameras = tuple(session.scene.cameras)
    assert "room" in cameras and "front" in cameras
    chosen = ["room"]  # the panel's first choice: the wide view, arm and table
    shown: list[np.ndarray] = []
    problems: list[str] = []
    feed = CameraFeed(lambda: current[0], cameras, lambda: chosen[0], shown.append, problems.append, hz=50.0,
                      pressure=lambda: None)  # the machine's own CPU pressure is the next test's
    feed.start()
    try:
        _wait(lambda: feed.frames >= 1 or problems)
        assert not problems, problems
        first = shown[0]
        assert first.shape == (144, 192, 3) and first.std() > 1.0  # a picture of something, not a blank
        _wait(lambda: feed.still >= 5)  # five more turns on the same snapshot: the picture stays as it is
        assert feed.frames == 1

        for _ in range(10):  # the arm moves 10 x 5 mm sideways
            panel.push(Command(translation=(0.0, 0.005, 0.0)))
            sim.step_once()
        current[0] = sim.snapshot
        _wait(lambda: feed.frames == 2)
        assert not np.array_equal(shown[-1], first)  # the new picture shows the arm where it went

        moved = feed.frames
        chosen[0] = "front"  # another camera: a new picture though nothing moved
        _wait(lambda: feed.frames > moved)
        assert shown[-1].shape == first.shape and not np.array_equal(shown[-1], shown[-2])
    finally:
        feed.stop()


def test_cpu_pressure_reads_the_kernels_figure(tmp_path):
    psi = tmp_path / "cpu"
    psi.write_text("some avg10=35.60 avg60=78.64 avg300=51.91 total=12185736565\n"
                   "full avg10=0.00 avg60=0.00 avg300=0.00 total=0\n")
    assert cpu_pressure(psi) == 35.6
    psi.write_text("nonsense\n")
    assert cpu_pressure(psi) is None
    assert cpu_pressure(tmp_path / "missing") is None
    here = cpu_pressure()  # this machine's own: a share of time, or None where the kernel has no PSI
    assert here is None or 0.0 <= here <= 100.0


def test_the_picture_yields_while_the_cpus_are_crowded():
    session = Session(scene="lift", robot="panda", control_hz=30.0)
    sim = SimThread(session, [], log=lambda message: None)
    snap = sim.step_once()
    pressure = [90.0]
    notes: list[str] = []
    problems: list[str] = []
    feed = CameraFeed(lambda: snap, tuple(session.scene.cameras), lambda: "room", lambda image: None, problems.append,
                      hz=50.0, pressure=lambda: pressure[0], busy_pressure=50.0, busy_hz=4.0, notice=notes.append)

    def looks_per_second() -> float:  # pictures made or found still: each a turn of the feed's loop
        start, t0 = feed.frames + feed.still, time.monotonic()
        time.sleep(1.0)
        return (feed.frames + feed.still - start) / (time.monotonic() - t0)

    feed.start()
    try:
        _wait(lambda: feed.frames >= 1 or problems)
        assert not problems, problems
        assert feed.crowded and "every 0.25 s while this machine's CPUs are busy (CPU pressure 50 % or more)" in notes[-1]
        assert looks_per_second() <= 6.0  # 4 a second, not 50
        pressure[0] = 20.0
        _wait(lambda: not feed.crowded)
        assert notes[-1] == ""  # the note goes
        rates = []  # back to its own rate: a second of it at 20 or more (on a loaded machine, some second soon)
        _wait(lambda: rates.append(looks_per_second()) or rates[-1] >= 20.0, 60.0)
        assert max(rates) >= 20.0, rates
    finally:
        feed.stop()
