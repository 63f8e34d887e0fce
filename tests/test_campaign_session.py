"""Issue 35: one operator's session in-process: seeds from the ledger, a reset after each save or
discard, every episode from its seed's initial state, provenance, and the move to the next task
when the operator's task has all it wants. Quick: one scene at a time, a few ticks per episode.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from devices.command import Command
from replay.episode import find_episodes, load_episode
from teleop.campaign.ledger import next_episode_index, next_seed
from teleop.campaign.operator_session import CampaignSession, SessionSpec
from teleop.campaign.progress import Progress
from teleop.control.recording import Recorder
from teleop.control.session import Session


def spec(out: Path, lift_wanted: int) -> SessionSpec:
    tasks = (("lift", lift_wanted, "lift", "panda", 30.0, None, "mcap"), ("stack", 2, "stack", "panda", 30.0, None, "mcap"),
             ("lift_ur5e", 9, "lift", "ur5e", 30.0, None, "mcap"))  # another robot: not this process's to take
    return SessionSpec(campaign="trial", session="s1-abc", operator="ana", task="lift", scene="lift", robot="panda",
                       out=str(out), port=0, wanted=lift_wanted, campaign_wanted=lift_wanted + 11, tasks=tasks)


def open_session(out: Path, lift_wanted: int) -> tuple[CampaignSession, Recorder, Progress]:
    s = spec(out, lift_wanted)
    progress: list[Progress] = []
    session = CampaignSession("lift", lambda task: next_seed(out, task), lambda task: next_episode_index(out, task),
                              lambda task: progress[0].next_task(task), scene="lift", robot="panda")
    progress.append(Progress(s, lambda: session.campaign_task))
    recorder = Recorder(session, out / "lift", verify="off", provenance=s.provenance)
    return session, recorder, progress[0]


def episode(session: CampaignSession, end: str, ticks: int = 4) -> None:
    session.step([Command(events=("start",))])
    for _ in range(ticks):
        session.step([Command(translation=np.array([0.01, 0.0, 0.0]))])
    session.step([Command(events=(end,))])


def test_each_episode_gets_a_fresh_seed_and_starts_from_its_initial_state(tmp_path):
    session, recorder, progress = open_session(tmp_path, lift_wanted=5)
    assert session.seed == 0
    for _ in range(3):  # driven before recording: the episode still starts from the seed's initial state
        session.step([Command(translation=np.array([0.01, 0.0, 0.0]))])
    episode(session, "save")
    assert session.seed == 1  # saved: the next seed
    episode(session, "discard")
    assert session.seed == 2  # discarded: the next seed too
    episode(session, "save")
    metas = [load_episode(p).meta for p in find_episodes([tmp_path / "lift"])]
    assert [m.seed for m in metas] == [0, 2]
    assert {(m.operator, m.campaign, m.session) for m in metas} == {("ana", "trial", "s1-abc")}
    first = load_episode(find_episodes([tmp_path / "lift"])[0])
    fresh = Session("lift", robot="panda", seed=0)  # the seed's initial state, as the first row records it
    assert np.array_equal(first.qpos[0], fresh.controller.data.qpos)
    assert "**0 of 5** successful episodes of `lift` (yours: 0); the campaign: **0 of 16**" in progress.line()
    assert progress.next_task("lift") is None  # lift still wants episodes


def test_a_task_with_all_it_wants_moves_the_operator_to_the_next_one(tmp_path):
    session, recorder, progress = open_session(tmp_path, lift_wanted=0)  # lift already has all it wants
    assert progress.next_task("lift") == ("stack", "stack")  # not lift_ur5e: another robot
    episode(session, "save")  # recorded on lift, then the reset moves on
    assert (session.campaign_task, session.scene_name) == ("stack", "stack")
    assert recorder.directory == tmp_path / "stack" and session.seed == 0  # stack's own seeds
    episode(session, "save")
    assert [load_episode(p).meta.scene for p in find_episodes([tmp_path / "stack"])] == ["stack"]
    progress.refresh()
    assert "successful episodes of `stack`" in progress.line()
