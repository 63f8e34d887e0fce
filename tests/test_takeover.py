"""Taking over from a policy (`teleop serve --policy`): the policy drives until a device moves the
arm, the operator hands back with a "policy" event (key p, the panel's button), every recorded step
says who drove, and the export writes LeRobot's `intervention` feature from it.

The policy here is a scripted one behind the policy interface (it moves the EE target up, then
holds): it drives visibly and the same way every time. A trained LeRobot checkpoint through the
same takeover is in tests/test_eval.py.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import teleop
from devices.command import Command
from devices.gizmo import GizmoDevice
from recorder.format import CONTROL_HUMAN, CONTROL_POLICY
from replay import load_episode
from replay.export import ExportOptions
from replay.export import export_dataset
from teleop.learn.gym_env import TeleopEnv
from teleop.control.loop import run_episode
from teleop.learn.policy import PolicyMismatch, ScriptedPolicy
from teleop.learn.takeover import Takeover, moves_arm
from teleop.web.session_page.serve_options import DEFAULT_STATUS_PERIOD_S
from teleop.web.session_page.panel import PanelDevice
from tests.browser import free_port
from tests.support import ROOT, assert_one_line_error, run_cli

RISE_M = 0.05  # the scripted policy lifts its target this much, then holds
POLICY_SCRIPT = {"steps": [{"duration": 1.0, "move": [0, 0, RISE_M]}, {"duration": 0.5}]}


@pytest.fixture(scope="module")
def script(tmp_path_factory):
    path = tmp_path_factory.mktemp("policy") / "rise.json"
    path.write_text(json.dumps(POLICY_SCRIPT))
    return path


def test_only_motion_and_gripper_count_as_a_touch():
    assert not moves_arm(Command(events=("start",)))
    assert not moves_arm(Command(events=("policy",)))
    assert not moves_arm(Command())
    assert moves_arm(Command(translation=np.array([0.0, 0.0, 1e-4])))
    assert moves_arm(Command(rotation=np.array([0.01, 0.0, 0.0])))
    assert moves_arm(Command(target_pos=np.zeros(3)))
    assert moves_arm(Command(gripper="close"))


@pytest.fixture(scope="module")
def taken_over(script, tmp_path_factory):
    """One recorded episode: 30 ticks of policy, a gizmo drag, 20 ticks of operator, hand back, 30 ticks of policy."""
    out = tmp_path_factory.mktemp("takeover")
    session = teleop.Session("lift", "panda", seed=3, control_hz=30)
    gizmo, panel = GizmoDevice(), PanelDevice()
    devices = [gizmo, panel]
    with teleop.Recorder(session, out / "eps", verify="sync", source="policy",
                         provenance={"policy": "script:rise.json"}) as rec:
        takeover = Takeover.for_session(session, ScriptedPolicy(script))
        start_target = session.controller.target_pose()[0].copy()
        rec.start()
        run_episode(session, devices, max_steps=30, record=False, steer=takeover.steer)
        policy_target = session.controller.target_pose()[0].copy()
        assert takeover.driver == "policy" and takeover.policy_steps == 30

        grab = policy_target + np.array([0.04, 0.0, 0.0])
        gizmo.push(0, grab, session.controller.target_pose()[1], "start")
        run_episode(session, devices, max_steps=20, record=False, steer=takeover.steer)
        operator_target = session.controller.target_pose()[0].copy()
        assert takeover.driver == "operator" and takeover.takeovers == 1

        panel.push(Command(events=("policy",)))  # the panel's button and the key `p` send this
        run_episode(session, devices, max_steps=30, record=False, steer=takeover.steer)
        assert takeover.driver == "policy"
        rec.save()
        takeover.close()
    return {"file": rec.paths[0], "takeover": takeover, "start": start_target, "policy": policy_target,
            "grab": grab, "operator": operator_target, "end": session.controller.target_pose()[0].copy(),
            "verified": dict(rec.verified), "out": out}


def test_the_policy_drives_until_a_device_moves_and_drives_again_when_handed_back(taken_over):
    t = taken_over
    # The policy lifted the target (30 of its 45 rise ticks), then the gizmo's pose won and stayed,
    # then the policy started afresh from the operator's pose and lifted again.
    assert t["policy"][2] - t["start"][2] == pytest.approx(RISE_M, abs=0.012)
    np.testing.assert_allclose(t["operator"], t["grab"], atol=1e-9)
    assert t["end"][2] - t["operator"][2] == pytest.approx(RISE_M, abs=0.012)
    np.testing.assert_allclose(t["end"][:2], t["operator"][:2], atol=1e-3)
    takeover = t["takeover"]
    assert takeover.policy_steps == 60 and takeover.operator_steps == 20
    assert [(h.step, h.driver) for h in takeover.handovers] == [(30, "operator"), (50, "policy")]
    assert takeover.handovers[0].reason == "gizmo moved"
    status = takeover.status()
    assert status["driver"] == "policy" and status["takeovers"] == 1
    assert status["inference_ms"] is not None and status["inference_max_ms"] >= status["inference_ms"] > 0


def test_every_recorded_step_says_who_drove_and_replays_bit_exact(taken_over):
    episode = load_episode(taken_over["file"])
    assert episode.meta.source == "policy" and episode.meta.policy == "script:rise.json"
    assert episode.meta.records_control and episode.steps == 80
    expected = np.array([CONTROL_POLICY] * 30 + [CONTROL_HUMAN] * 20 + [CONTROL_POLICY] * 30)
    np.testing.assert_array_equal(episode.control, expected)
    assert taken_over["verified"] == {str(taken_over["file"]): True}
    assert teleop.resimulate(episode).bit_exact


def test_export_writes_intervention_from_who_drove(taken_over, tmp_path):
    from lerobot.datasets import LeRobotDataset

    # A takeover episode beside a plain human one (no control field): the feature covers both.
    human = teleop.Session("lift", "panda", seed=4, control_hz=30)
    with teleop.Recorder(human, taken_over["out"] / "human", verify="off") as rec:
        run_episode(human, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")], max_steps=25)
    files = [taken_over["file"], rec.paths[0]]
    summary = export_dataset(files, ExportOptions(out=tmp_path / "ds", repo_id="t/dagger", cameras=[], progress=False))
    assert summary.frames == 80 + 25
    ds = LeRobotDataset("t/dagger", root=tmp_path / "ds")
    feature = ds.meta.features["intervention"]
    assert feature["dtype"] == "bool" and tuple(feature["shape"]) == (1,)
    column = np.asarray(ds.hf_dataset.with_format("numpy")["intervention"]).reshape(-1)
    np.testing.assert_array_equal(column, [False] * 30 + [True] * 20 + [False] * 30 + [True] * 25)

    # Without takeover episodes there is no such feature; appending them to such a dataset keeps it absent...
    plain = export_dataset([rec.paths[0]], ExportOptions(out=tmp_path / "plain", repo_id="t/plain", cameras=[],
                                                         progress=False))
    assert plain.frames == 25
    assert "intervention" not in LeRobotDataset("t/plain", root=tmp_path / "plain").meta.features
    # ...and appending to a dataset that has it writes it for human episodes too.
    export_dataset([rec.paths[0]], ExportOptions(out=tmp_path / "ds", repo_id="t/dagger", cameras=[], append=True,
                                                 progress=False))
    column = np.asarray(LeRobotDataset("t/dagger", root=tmp_path / "ds").hf_dataset.with_format("numpy")["intervention"])
    assert column.reshape(-1)[-25:].all() and len(column) == 130


def test_a_scripted_policy_needs_ee_actions_and_a_failing_policy_hands_over(script):
    session = teleop.Session("lift", "panda", seed=0, control_hz=30)

    class Broken(ScriptedPolicy):
        def select_action(self, observation):
            raise RuntimeError("the network produced NaNs\nsecond line")

    takeover = Takeover.for_session(session, Broken(script))
    try:
        commands, ctrl = takeover.steer(session, [])
        assert commands == [] and ctrl is None
        assert takeover.driver == "operator" and takeover.problem == "the network produced NaNs"
        assert any("policy stopped" in m for m in session.stats.messages)
        takeover.request("policy")  # a broken policy cannot be handed control again
        takeover.steer(session, [])
        assert takeover.driver == "operator"
    finally:
        takeover.close()
    env = TeleopEnv(session=session, action="joint", cameras=())
    with pytest.raises(PolicyMismatch, match="EE actions"):
        Takeover(session, ScriptedPolicy(script), env)
    env.close()


def test_serve_policy_errors_are_one_line(tmp_path):
    port = str(free_port())
    result = run_cli("serve", "--policy", str(tmp_path / "nope"), "--port", port)
    assert_one_line_error(result, "no such policy folder")
    result = run_cli("serve", "--policy", f"script:{tmp_path / 'nope.json'}", "--port", port)
    assert_one_line_error(result, "no such script file")


def test_dragging_the_gizmo_in_the_browser_takes_over_and_the_recording_says_so(script, tmp_path):
    """`teleop serve --policy` in headless Chromium: the policy drives, a gizmo drag takes over,
    the panel's button hands back, and the saved episode's steps say who drove each one."""
    from playwright.sync_api import sync_playwright

    import tests.browser as headless

    record = tmp_path / "eps"
    home_z = teleop.Session("lift", "panda", seed=0).controller.target_pose()[0][2]
    server = headless.ServeProcess(["--policy", f"script:{script}", "--record", str(record), "--device", "gizmo"], tmp_path)
    try:
        with sync_playwright() as pw:
            browser = headless.launch(pw)
            page = headless.open_page(browser, server.url)
            server.wait_for(lambda s: s["clients"] >= 1, what="the page to connect")
            headless.dismiss_toasts(page)
            # The policy drives from the start: it lifts the target and holds it.
            held = server.wait_for(lambda s: s["driver"] == "policy" and s["policy"]["policy_steps"] > 50,
                                   what="the policy to drive", timeout_s=30)
            assert held["target_pos"][0][2] == pytest.approx(home_z + RISE_M, abs=0.01)
            page.get_by_text("Driving: policy").first.wait_for(timeout=60000)
            page.get_by_text("Inference:").first.wait_for(timeout=60000)
            headless.click_button(page, "Record")
            # Record starts the episode from the seed's initial state (the arm home) and the policy from its start:
            # it lifts the target again, and holds it
            server.wait_for(lambda s: s["recording"] and s["episode_steps"] > 10 and s["target_pos"][0][2] > home_z + RISE_M - 0.01,
                            what="recording under the policy")

            before = np.array(server.status()["target_pos"][0])
            headless.drag_gizmo_axis(page, before, server.status()["target_quat"][0], axis=0, pixels=80)
            taken = server.wait_for(lambda s: s["driver"] == "operator", what="the drag to take over")
            assert taken["policy"]["takeovers"] == 1 and taken["policy"]["handovers"][-1]["reason"] == "gizmo moved"
            server.wait_for(lambda s: s["target_pos"][0][0] > before[0] + 0.03, what="the dragged target")
            page.get_by_text("Driving: operator").first.wait_for(timeout=60000)
            time.sleep(0.5)  # some operator steps
            # Where the operator left it: the drag's last pointer moves may land after the first status past +3 cm.
            moved = server.status()
            for _ in range(40):  # until two statuses a status period apart agree
                time.sleep(2 * DEFAULT_STATUS_PERIOD_S)
                now = server.status()
                if now["target_pos"] == moved["target_pos"]:
                    break
                moved = now
            operator_z = moved["target_pos"][0][2]

            headless.click_button(page, "Hand back to policy")
            back = server.wait_for(lambda s: s["driver"] == "policy" and s["target_pos"][0][2] > operator_z + RISE_M - 0.01,
                                   what="the policy to drive again from the operator's pose", timeout_s=30)
            assert back["target_pos"][0][0] == pytest.approx(moved["target_pos"][0][0], abs=0.01)
            headless.click_button(page, "Stop")
            saved = server.wait_for(lambda s: s["episodes_saved"] == 1 and all(v is not None for v in s["verified"].values())
                                    and s["verified"], what="the save and its replay check")
            assert list(saved["verified"].values()) == [True]
            browser.close()
    finally:
        assert server.stop() == 0, server.log()[-3000:]
    episode = load_episode(sorted(record.glob("*.mcap"))[0])
    assert episode.meta.source == "policy" and episode.meta.policy == f"script:{script.name}"
    control = episode.control
    # policy, then the operator from the drag on, then the policy again: exactly two changes
    changes = np.flatnonzero(np.diff(control))
    assert control[0] == CONTROL_POLICY and control[-1] == CONTROL_POLICY and len(changes) == 2
    assert (control[changes[0] + 1:changes[1] + 1] == CONTROL_HUMAN).all()
    # the target moves along x under the operator, not while the policy held it
    x = episode.ee_target[:, 0, 0]
    np.testing.assert_allclose(x[:changes[0] + 1], before[0], atol=1e-6)
    assert x[changes[0] + 1:changes[1] + 1].max() > before[0] + 0.03


def test_inspect_shows_who_drove(taken_over):
    from tests.support import run_json

    info = run_json("inspect", str(taken_over["file"]), "--json")
    assert info["source"] == "policy" and info["policy"] == "script:rise.json"
    assert info["control"] == {"policy_steps": 60, "operator_steps": 20, "takeovers": 1}
