"""Issue 35: a campaign in real processes: two operators, each in a session of their own.

One `teleop campaign` process; operators join by the API and drive their arms through the
input websocket as a page does (key presses). Checked: each session records into out/<task>/
with its operator's provenance and seeds of its own; one operator's token opens no other
session; a kill -9 of one session leaves the other driving and recording, and the operator
can join again; a kill -9 of the campaign leaves no session process behind; a restart keeps
the counts and the seeds going.
"""

from __future__ import annotations

import http.client
import json
import signal
import subprocess
import threading
import time
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from websockets.exceptions import InvalidStatus
from websockets.sync.client import connect

from replay.episode import EpisodeError, find_episodes, load_episode
from tests.support import CampaignProcess, alive, campaign_session_status, children_of, run_json, wait_until

pytestmark = pytest.mark.e2e
CAMPAIGN = 'name = "trial"\nout = "data"\nmax_sessions = 2\nsession_minutes = 10\n[[task]]\nscene = "lift"\nepisodes = 5\n'


def press(ws, key: str, hold_s: float = 0.05) -> None:
    ws.send(json.dumps({"type": "key", "key": key, "down": True}))
    time.sleep(hold_s)
    ws.send(json.dumps({"type": "key", "key": key, "down": False}))


def record_one(joined: dict, out: Path) -> None:
    """Drive the arm by keys over the session's input websocket: record, move, save."""
    with connect(joined["input"], open_timeout=60) as ws:
        press(ws, "b")
        wait_until(lambda: campaign_session_status(out, joined["session"]).get("recording"), 60, "recording to start")
        press(ws, "w", 0.6)
        press(ws, "Enter")
        wait_until(lambda: campaign_session_status(out, joined["session"]).get("episodes_saved", 0) >= 1, 60, "the save")


def readable(path: Path):
    """The episode at `path`, or None while it is too new to have its metadata (another session's, being written)."""
    try:
        return load_episode(path)
    except EpisodeError:
        return None


def runs_a_session(pid: int) -> bool:
    """Whether process `pid` is (still) a campaign session process, not a zombie."""
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
        return state != "Z" and "campaign_session" in Path(f"/proc/{pid}/cmdline").read_text(errors="replace")
    except OSError:
        return False


def test_two_operators_record_apart_and_faults_stay_in_their_session(tmp_path):
    file = tmp_path / "week.toml"
    file.write_text(CAMPAIGN)
    out = tmp_path / "data"
    campaign = CampaignProcess(file)
    try:
        answers: dict[str, tuple[int, dict]] = {}
        threads = [threading.Thread(target=lambda n=n: answers.__setitem__(n, campaign.join(n))) for n in ("ana", "bo")]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert [answers[n][0] for n in ("ana", "bo")] == [200, 200], (answers, campaign.log())
        ana, bo = answers["ana"][1], answers["bo"][1]
        assert set(ana) >= {"operator", "task", "instruction", "url", "xr", "token", "input"}
        assert (ana["operator"], ana["task"], ana["instruction"]) == ("ana", "lift", "Pick up the red cube and lift it.")
        assert ana["token"] != bo["token"] and urlsplit(ana["url"]).port != urlsplit(bo["url"]).port

        # The join answer offers the session's XR page (a headset's browser opens it), under the session's token.
        xr = urlsplit(ana["xr"])
        conn = http.client.HTTPConnection("127.0.0.1", xr.port, timeout=30)
        conn.request("GET", f"{xr.path}?{xr.query}")
        page = conn.getresponse()
        assert xr.port == urlsplit(ana["url"]).port and page.status == 200 and b"Enter VR" in page.read()
        conn.close()

        # One operator's token opens no other session: neither its page nor its input websocket.
        bo_port = urlsplit(bo["url"]).port
        conn = http.client.HTTPConnection("127.0.0.1", bo_port, timeout=30)
        conn.request("GET", f"/?token={ana['token']}")
        assert conn.getresponse().status == 403
        conn.close()
        with pytest.raises(InvalidStatus) as refused:
            connect(bo["input"].replace(bo["token"], ana["token"]), open_timeout=30)
        assert refused.value.response.status_code == 403

        # Beyond max_sessions: a place in the queue; a name already live: refused with a reason.
        assert campaign.join("cy") == (202, {"queue": 1})
        status, answer = campaign.join("ana")
        assert status == 409 and "already in a live session" in answer["error"]

        recorders = [threading.Thread(target=record_one, args=(j, out)) for j in (ana, bo)]
        for t in recorders:
            t.start()
        for t in recorders:
            t.join()
        episodes = [load_episode(p).meta for p in find_episodes([out / "lift"])]
        assert sorted(m.operator for m in episodes) == ["ana", "bo"]
        assert {m.campaign for m in episodes} == {"trial"}
        assert sorted(m.session for m in episodes) == sorted([ana["session"], bo["session"]])
        assert len({m.seed for m in episodes}) == 2
        seeds_after_save = {campaign_session_status(out, j["session"])["seed"] for j in (ana, bo)}  # each reset to its next seed
        assert not seeds_after_save & {m.seed for m in episodes} and len(seeds_after_save) == 2
        shown = run_json("inspect", str(find_episodes([out / "lift"])[0]), "--json")
        assert shown["operator"] in ("ana", "bo") and shown["campaign"] == "trial" and shown["session"]
        wait_until(lambda: all(s["episodes"] == 1 for s in campaign.status()["sessions"]), 30, "the counts on the admin status")
        table = {s["operator"]: s for s in campaign.status()["sessions"]}
        assert table["ana"]["state"] == table["bo"]["state"] == "live"
        assert "successful episodes of `lift` (yours: 0); the campaign: **0 of 5**" in campaign_session_status(out, ana["session"])["headline"]
        assert table["ana"]["realtime_factor"] > 0.5 and table["ana"]["pid"] != table["bo"]["pid"]

        # kill -9 of ana's session mid-episode: bo's goes on recording; ana's episode so far is readable.
        with connect(ana["input"], open_timeout=30) as ws:
            press(ws, "b")
            wait_until(lambda: campaign_session_status(out, ana["session"]).get("episode_steps", 0) > 60, 60, "ana's steps")
        with connect(bo["input"], open_timeout=30) as ws:
            press(ws, "b")
            wait_until(lambda: campaign_session_status(out, bo["session"]).get("recording"), 60, "bo recording")
        ana_pid = table["ana"]["pid"]
        subprocess.run(["kill", "-9", str(ana_pid)], check=True)
        wait_until(lambda: campaign.session(ana["session"])["state"] == "ended", 30, "ana's session shown ended")
        steps = campaign_session_status(out, bo["session"])["episode_steps"]
        wait_until(lambda: campaign_session_status(out, bo["session"]).get("episode_steps", 0) > steps + 30, 60, "bo recording on")
        assert campaign.session(bo["session"])["state"] == "live"
        cut = [e for e in map(readable, find_episodes([out / "lift"])) if e is not None and e.meta.operator == "ana"]
        assert len(cut) == 2 and max(e.steps for e in cut) > 0  # the killed episode reads as today (cut short)

        status, again = campaign.join("ana")  # ana may join again: cy waits, but ana's slot was hers
        assert status in (200, 202), again
        children = children_of(campaign.proc.pid)
        assert len(children) >= 1

        # kill -9 of the campaign: no session process is left.
        campaign.proc.send_signal(signal.SIGKILL)
        campaign.proc.wait(30)
        wait_until(lambda: not any(alive(pid, started) for pid, started in children.items()), 60,
                   "every session process to end with its campaign")
    finally:
        campaign.stop()

    # A restart continues the counts and the seeds.
    before = len(find_episodes([out / "lift"]))
    again = CampaignProcess(file)
    try:
        tasks = again.status()["tasks"]
        assert tasks[0]["episodes"] == before >= 3 and tasks[0]["wanted"] == 5
        used = {load_episode(p).meta.seed for p in find_episodes([out / "lift"])}
        status, joined = again.join("dee")
        assert status == 200, (joined, again.log())
        assert campaign_session_status(out, joined["session"])["seed"] > max(used)
        children = children_of(again.proc.pid)
        assert children
    finally:
        again.stop()  # Ctrl-C: every session ends with the campaign
    assert again.proc.returncode == 0, again.log()
    assert not any(alive(pid, started) for pid, started in children.items())


def test_export_writes_the_operator_and_takes_only_the_ones_asked_for(tmp_path):
    """`teleop export --operator NAME[,NAME]`: only their episodes, with an `operator` column in the episode metadata."""
    import pyarrow.parquet as pq

    from teleop.control.recording import Recorder
    from teleop.control.session import Session
    from tests.support import run_cli

    session = Session("lift", seed=0)
    recorder = Recorder(session, tmp_path / "eps", verify="off")
    for operator in ("ana", "bo", "cy", None):
        recorder.provenance = {"operator": operator, "campaign": "trial", "session": f"s-{operator}"} if operator else {}
        recorder.start()
        for _ in range(5):
            session.step()
        recorder.save()
        session.reset()
    assert [load_episode(p).meta.operator for p in find_episodes([tmp_path / "eps"])] == ["ana", "bo", "cy", None]
    out = tmp_path / "ds"
    result = run_cli("export", str(tmp_path / "eps"), "--out", str(out), "--repo-id", "t/ops", "--image-size", "32x32",
                     "--no-video", "--operator", "cy,ana")
    assert result.returncode == 0, result.stderr
    table = pq.read_table(sorted((out / "meta" / "episodes").rglob("*.parquet"))[0])
    assert table.column("operator").to_pylist() == ["ana", "cy"]
    result = run_cli("export", str(tmp_path / "eps"), "--out", str(tmp_path / "none"), "--repo-id", "t/ops", "--operator", "dee")
    assert result.returncode == 2 and "no episodes recorded by dee" in result.stderr and not (tmp_path / "none").exists()


def test_sessions_run_as_ray_actors_on_both_nodes_of_a_local_cluster(tmp_path):
    """`--ray ADDRESS`: a two-node local cluster (one CPU each) takes one session on each node; the
    lobby stays here, the sessions record into the same out/, and they end with the campaign."""
    from ray.cluster_utils import Cluster

    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "include_dashboard": False})
    cluster.add_node(num_cpus=1)
    try:
        file = tmp_path / "week.toml"
        file.write_text(CAMPAIGN)
        out = tmp_path / "data"
        campaign = CampaignProcess(file, "--ray", cluster.address)
        try:
            answers = [campaign.join(name) for name in ("ana", "bo")]
            assert [status for status, _ in answers] == [200, 200], (answers, campaign.log())
            sessions = campaign.status()["sessions"]
            assert len({s["node"] for s in sessions}) == 2 and {s["state"] for s in sessions} == {"live"}
            record_one(answers[0][1], out)
            assert [load_episode(p).meta.operator for p in find_episodes([out / "lift"])] == ["ana"]
            pids = {s["pid"] for s in sessions}
        finally:
            campaign.stop()
        assert campaign.proc.returncode == 0, campaign.log()
        wait_until(lambda: not any(map(runs_a_session, pids)), 60, "the session processes to end with the campaign")
    finally:
        cluster.shutdown()
