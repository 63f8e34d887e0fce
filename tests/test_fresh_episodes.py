"""Issue 49, item 1 in-process: in `teleop serve` (Session.fresh_episodes) Save, Stop and Discard move to the
next seed with the arm home, every episode starts from its seed's initial state, the recorded seed is the one
the episode started from, `--keep-scene` keeps the old behaviour, and the browser session's loop restarts the
devices that play from the beginning (a script; a leader arm's ease-in) on every new scene.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from devices.command import Command
from devices.script import ScriptDevice
from replay.episode import find_episodes, load_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session
from tests.support import ROOT

pytestmark = pytest.mark.unit

NUDGE = Command(translation=np.array([0.01, 0.0, 0.0]))  # 1 cm a tick along +x (world frame)


def initial_qpos(seed: int) -> np.ndarray:
    """The seed's initial state: what a freshly built scene holds before its first tick."""
    return Session("lift", robot="panda", seed=seed).controller.data.qpos.copy()


def drive(session: Session, ticks: int = 5) -> None:
    for _ in range(ticks):
        session.step([NUDGE])


def test_save_and_discard_move_to_the_next_seed_and_every_episode_starts_from_its_seed(tmp_path: Path):
    session = Session("lift", robot="panda", seed=3, fresh_episodes=True)
    Recorder(session, tmp_path, verify="off")
    drive(session)  # driven before recording: the episode still starts from seed 3's initial state
    session.step([Command(events=("record",))])
    drive(session)
    session.step([Command(events=("record",))])  # Stop saves
    assert session.seed == 4 and session.controller.data.time == pytest.approx(session.dt)  # the save's tick ran on it
    now, start = session.controller.data.qpos, initial_qpos(4)
    np.testing.assert_allclose(now[:7], start[:7], atol=1e-3)  # the arm's 7 joints home (rad); the fingers open a little
    np.testing.assert_allclose(now[9:], start[9:], atol=1e-3)  # the cube where seed 4 puts it (m, quaternion)
    session.step([Command(events=("start",))])
    drive(session)
    session.step([Command(events=("discard",))])
    assert session.seed == 5
    session.step([Command(events=("save",))])  # nothing recording: nothing moves
    assert session.seed == 5
    files = find_episodes([tmp_path])
    assert len(files) == 1
    episode = load_episode(files[0])
    assert episode.meta.seed == 3  # the seed it started from
    np.testing.assert_array_equal(episode.qpos[0], initial_qpos(3))


def test_keep_scene_leaves_the_arm_where_it_was(tmp_path: Path):
    session = Session("lift", robot="panda", seed=3)  # fresh_episodes off: teleop serve --keep-scene, teleop run
    Recorder(session, tmp_path, verify="off")
    session.step([Command(events=("start",))])
    drive(session)
    session.step([Command(events=("save",))])
    assert session.seed == 3 and session.controller.data.time > 0
    assert not np.array_equal(session.controller.data.qpos, initial_qpos(3))
    drive(session)
    session.step([Command(events=("start",))])  # the next episode starts where the arm is
    assert session.controller.data.time > 0


def test_a_new_scene_drops_the_targets_read_against_the_old_one(tmp_path: Path):
    session = Session("lift", robot="panda", seed=0, fresh_episodes=True)
    Recorder(session, tmp_path, verify="off")
    home = session.controller.joint_targets(0).copy()  # radians, the seed's initial targets
    drive(session)
    bent = home + 0.3  # radians: far from home, as a leader arm held somewhere else would ask
    far = Command(target_pos=session.controller.target_pose(0)[0] + 0.1)  # m: an absolute target read before
    session.step([Command(events=("start",)), Command(joints=bent), far])  # the start goes back to the initial state
    np.testing.assert_allclose(session.controller.joint_targets(0), home, atol=0.02)  # held home, no jump
    np.testing.assert_allclose(session.controller.target_pose(0)[0], Session("lift", robot="panda").controller.target_pose(0)[0])
    session.step([Command(joints=bent)])  # from the next tick the device's targets apply
    assert np.abs(session.controller.joint_targets(0) - home).max() > 0.2


def test_the_browser_loop_restarts_script_devices_on_every_new_scene(tmp_path: Path):
    from teleop.web.session_page.panel import PanelDevice
    from teleop.web.session_page.sim_thread import SimThread

    session = Session("lift", robot="panda", seed=0, fresh_episodes=True)
    Recorder(session, tmp_path, verify="off")
    script = ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")
    script.start()
    panel = PanelDevice()
    sim = SimThread(session, [script, panel], log=lambda line: None)
    for _ in range(20):
        sim.step_once()
    assert script.index > 0 or script.elapsed > 0  # the script played
    model = session.controller.model
    panel.push(Command(events=("record",)))
    snap = sim.step_once()  # the start went back to the seed's initial state: the script begins again
    assert sim.device_restarts == 1 and script.index == 0 and script.elapsed == 0.0
    assert snap.model is model and snap.generation == 0  # the same compiled model: pages and cameras keep theirs
    for _ in range(10):
        sim.step_once()
    panel.push(Command(events=("record",)))
    snap = sim.step_once()  # saved: the next seed, the script from its first step again
    assert sim.device_restarts == 2 and snap.seed == 1 and script.index == 0 and script.elapsed == 0.0
    assert snap.generation == 1 and not snap.recording  # a new model: the next seed's placement
