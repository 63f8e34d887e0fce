"""A real SO-101 follower mirrors the simulated so101 (issue 47 item 3), through LeRobot's own `SOFollower`.

The follower is the byte-level Feetech emulator on a pseudo-terminal (tests/servo_emulator.py), started far from
the simulated pose; LeRobot is real and unpatched. What is checked is what reached the servos: the
Goal_Position writes ease in at no more than max_step degrees a tick per joint, then follow the simulated arm's
targets, and Torque_Enable 0 reaches every servo when the session ends (script end, Ctrl-C, SIGTERM, serve
stopped). Bad pairings and ports are one line, exit 2.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from devices.base import DeviceError
from devices.command import Command
from replay import load_episode
from teleop.control.follower import Follower, open_follower
from teleop.control.follower_spec import check_pairing, leader_map_of, motor_map, parse_follower_spec
from teleop.control.session import Session
from teleop.errors import UsageError
from devices.joint_map import builtin_map_path
from tests.servo_emulator import MOTOR_NAMES, FeetechEmulator
from tests.support import ROOT, assert_one_line_error, run_cli, run_main, wait_until, write_script

pytestmark = pytest.mark.e2e

MAX_STEP_DEG = 5.0
STEP_RAW = MAX_STEP_DEG * 4095 / 360 + 1  # the largest change of an arm joint's goal between two writes, raw steps
RATE = 3000  # raw steps/s the emulated servos move at (an STS3215 at 12 V turns about 270 deg/s)
# Far from the simulated so101's home pose (0, 9, -5, 87, 0 degrees): up to 87 degrees off, the jaws shut.
FAR = {1: 1250, 2: 2800, 3: 1300, 4: 2000, 5: 2600, 6: 2020}
ID = "follower_arm"


def start_follower(tmp_path: Path, **kwargs) -> tuple[FeetechEmulator, Path]:
    arm = FeetechEmulator.start(tmp_path, role="follower", rate=RATE, positions=FAR, **kwargs)
    cal = tmp_path / "cal"
    arm.write_calibration_file(cal, ID)
    return arm, cal


def spec_of(arm: FeetechEmulator, cal: Path) -> str:
    return f"so101_follower:{arm.port}:id={ID}:calibration={cal}:max_step={MAX_STEP_DEG:g}"


def goal_rows(arm: FeetechEmulator) -> list[tuple[float, dict[int, int]]]:
    """The Goal_Position sync writes, in order: (time, {id: raw})."""
    rows: dict[float, dict[int, int]] = {}
    for w in arm.goal_log():
        rows.setdefault(w["t"], {})[w["id"]] = w["raw"]
    return sorted(rows.items())


def step_raw(arm: FeetechEmulator, servo: int) -> float:
    """max_step in raw steps: degrees for the arm joints; for the gripper LeRobot's 0..100 over its range."""
    motor, cal = arm.motor_of(servo)
    return STEP_RAW if motor != "gripper" else MAX_STEP_DEG / 100 * (cal.range_max - cal.range_min) + 1


def assert_eased(arm: FeetechEmulator, start: dict[int, int]) -> list[dict[int, int]]:
    """No joint's goal ever moved more than max_step from the one before (the first from where the servo was)."""
    goals = [g for _, g in goal_rows(arm)]
    assert goals, "no Goal_Position was written"
    previous = dict(start)
    for k, goal in enumerate(goals):
        assert set(goal) == set(range(1, 7)), goal
        for i, raw in goal.items():
            assert abs(raw - previous[i]) <= step_raw(arm, i), f"goal {k}: servo {i} jumped {previous[i]} -> {raw}"
        previous = goal
    return goals


def assert_torque_off_at_end(arm: FeetechEmulator) -> None:
    """Every servo got Torque_Enable 0 after the last goal."""
    last_goal = max(w["t"] for w in arm.goal_log())
    off = {w["id"] for w in arm.torque_log() if w["value"] == 0 and w["t"] >= last_goal}
    assert off == set(range(1, 7)), arm.torque_log()[-8:]


def raw_targets(arm: FeetechEmulator, ctrl: np.ndarray) -> dict[int, int]:
    """A recorded so101 ctrl row (5 joints rad, gripper rad 0 closed .. 0.55 open) as the raw goals LeRobot writes."""
    action = {f"{m}.pos": math.degrees(v) for m, v in zip(MOTOR_NAMES[:5], ctrl[:5])}
    action["gripper.pos"] = 100.0 * min(max(ctrl[5] / 0.55, 0.0), 1.0)
    return arm.raw_of(action)


# --- the command line ---------------------------------------------------------------------------------------

def test_run_eases_the_follower_in_then_it_follows_the_simulated_arm(tmp_path: Path):
    arm, cal = start_follower(tmp_path)
    with arm:
        script = write_script(tmp_path / "s.json", [
            {"duration": 1.0, "gripper": "open"},  # hold still while the follower comes over
            {"duration": 1.5, "move": [0.04, 0.05, 0.04]},
            {"duration": 1.0, "gripper": "open"},  # and at the end: a sender slowed by a loaded machine catches up
        ])
        started = time.monotonic()
        result = run_cli("run", "--device", f"script:{script}", "--robot", "so101", "--follower", spec_of(arm, cal),
                         "--record", str(tmp_path / "rec"), "--json", timeout=240)
        assert result.returncode == 0, result.stderr[-3000:]
        summary = json.loads(result.stdout)
        # the session ran in wall-clock time (3.5 s of script), not flat out
        assert summary["wall_seconds"] >= 3.3 and time.monotonic() - started >= 3.3
        follower = summary["follower"]
        # goals went out all along (105 ticks at 30 Hz; a loaded machine may merge a few), none clamped
        assert follower["state"] == "tracking" and follower["sent"] >= 40 and follower["clamped"] == 0, follower
        goals = assert_eased(arm, FAR)
        assert_torque_off_at_end(arm)
        episode = load_episode(Path(summary["files"][0]))
        targets = [raw_targets(arm, row) for row in episode.ctrl]
        # easing in: the wrist, 87 degrees off, needs 17 goals to get there, the gripper (shut, to open) 20; the
        # first goal on one of the simulated targets (a sender slowed by a loaded machine may still be easing when
        # the hold ends, and then meets the arm while it moves)
        def on_target(goal: dict[int, int]) -> bool:
            return any(all(abs(goal[i] - t[i]) <= 2 for i in range(1, 7)) for t in targets)

        first_on_target = next((k for k, g in enumerate(goals) if on_target(g)), None)
        assert first_on_target is not None, f"no goal reached the simulated arm's targets: last {goals[-1]}"
        assert first_on_target >= 19
        # then every goal heads for one of the simulated arm's targets: it is that target (to the raw step LeRobot
        # truncates to), or held back on the way from the goal before by LeRobot's max_relative_target, which
        # counts from the servo's present position (a servo process starved on a loaded machine reports it late)
        def off_the_way(goal: dict[int, int], before: dict[int, int], target: dict[int, int]) -> int:
            return max(max(0, min(before[i], target[i]) - goal[i], goal[i] - max(before[i], target[i])) for i in range(1, 7))

        exact = 0
        for k in range(first_on_target + 2, len(goals)):
            goal, before = goals[k], goals[k - 1]
            gap = min(off_the_way(goal, before, t) for t in targets)
            assert gap <= 2, f"goal {k} {goal} heads for none of the simulated targets (nearest {gap} raw steps off)"
            exact += min(max(abs(goal[i] - t[i]) for i in range(1, 7)) for t in targets) <= 2
        assert exact >= (len(goals) - first_on_target - 2) // 2, "most goals are the simulated targets themselves"
        # and the arm moved with the script: the last goal is the end of the move, far from where the hold was
        assert max(abs(goals[-1][i] - targets[0][i]) for i in range(1, 6)) > 30
        assert max(abs(goals[-1][i] - targets[-1][i]) for i in range(1, 7)) <= 8


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_an_interrupted_run_disables_torque(tmp_path: Path, sig: int):
    arm, cal = start_follower(tmp_path)
    with arm:
        script = write_script(tmp_path / "s.json", [{"duration": 120.0, "move": [0.0, 0.05, 0.0]}])
        # PYTHONFAULTHANDLER: should it hang after the signal, SIGABRT makes it print where each thread waits
        env = {**os.environ, "PYTHONPATH": str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""),
               "PYTHONFAULTHANDLER": "1"}
        # Ctrl-C as in a terminal: a suite started in the background (`cmd &` in a script) runs with SIGINT ignored,
        # which the run would inherit and keep, as a background job does
        proc = subprocess.Popen([sys.executable, "-m", "teleop", "run", "--device", f"script:{script}", "--robot", "so101",
                                 "--follower", spec_of(arm, cal)], cwd=ROOT, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
        try:
            wait_until(lambda: len(goal_rows(arm)) >= 10 or proc.poll() is not None, 120, "goals sent to the follower")
            assert proc.poll() is None, proc.communicate()[1][-2000:]
            assert not any(w["value"] == 0 for w in arm.torque_log() if w["t"] > goal_rows(arm)[0][0])
            proc.send_signal(sig)
            try:
                _, err = proc.communicate(timeout=180)
            except subprocess.TimeoutExpired:
                proc.send_signal(signal.SIGABRT)
                _, err = proc.communicate(timeout=30)
                raise AssertionError(f"teleop run did not end within 180 s of {sig.name}; its threads:\n{err[-6000:]}")
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        assert proc.returncode == 130, err[-2000:]
        assert "Traceback" not in err
        assert_eased(arm, FAR)
        assert_torque_off_at_end(arm)


def test_serve_shows_the_follower_and_disables_torque_when_stopped(tmp_path: Path):
    from tests.browser import ServeProcess

    arm, cal = start_follower(tmp_path)
    with arm:
        server = ServeProcess(["--robot", "so101", "--device", "gizmo", "--follower", spec_of(arm, cal)], tmp_path,
                              env={"PYTHONPATH": str(ROOT)})
        try:
            status = server.wait_for(lambda s: (s.get("follower") or {}).get("state") == "tracking", 60, "tracking")
            follower = status["follower"]
            assert follower["max_gap_deg"] is not None and follower["max_gap_deg"] < 3.0
            assert follower["sent"] > 10 and follower["clamped"] == 0
        finally:
            code = server.stop(signal.SIGTERM)
        assert code == 0, server.log()[-2000:]
        assert_eased(arm, FAR)
        assert_torque_off_at_end(arm)


def test_a_follower_pairs_only_with_its_own_robot(tmp_path: Path):
    result = run_main("run", "--device", "script:x.json", "--robot", "panda", "--follower", "so101_follower:/dev/ttyACM0")
    assert_one_line_error(result, "so101_follower", "so101", "panda")


def test_a_missing_port_is_one_line(tmp_path: Path):
    script = write_script(tmp_path / "s.json", [{"duration": 0.5}])
    result = run_main("run", "--device", f"script:{script}", "--robot", "so101", "--record", str(tmp_path / "rec"),
                      "--follower", f"so101_follower:{tmp_path / 'ttyNOPE'}")
    assert_one_line_error(result, "ttyNOPE", "no such serial port")
    assert not (tmp_path / "rec").exists() or not any((tmp_path / "rec").iterdir())  # nothing was recorded


def test_a_wrong_servo_model_is_one_line(tmp_path: Path):
    arm, cal = start_follower(tmp_path, model={1: 777, 2: 777, 3: 1234, 4: 777, 5: 777, 6: 777})
    with arm:
        script = write_script(tmp_path / "s.json", [{"duration": 0.5}])
        result = run_cli("run", "--device", f"script:{script}", "--robot", "so101", "--follower", spec_of(arm, cal))
        assert_one_line_error(result, arm.port, "elbow_flex", "1234", "SO-101")
        assert arm.goal_log() == [] and not any(w["value"] == 1 for w in arm.torque_log())  # never energised


# --- the Python API -----------------------------------------------------------------------------------------

def test_spec_parsing():
    spec = parse_follower_spec("so101_follower:/dev/ttyACM0:id=left:calibration=/tmp/c:max_step=2.5")
    assert (spec.port, spec.id, str(spec.calibration), spec.max_step_deg) == ("/dev/ttyACM0", "left", "/tmp/c", 2.5)
    assert parse_follower_spec("so101_follower:/dev/ttyACM0").max_step_deg == 5.0
    for bad in ("so101_follower", "koch_follower:/dev/x", "so101_follower:/dev/x:speed=3", "so101_follower:/dev/x:max_step=0"):
        with pytest.raises(UsageError):
            parse_follower_spec(bad)
    with pytest.raises(UsageError, match="add --robot so101"):
        check_pairing(spec, "ur5e")


def test_missing_or_mismatched_calibration_names_lerobot_calibrate(tmp_path: Path):
    arm, cal = start_follower(tmp_path)
    with arm:
        session = Session("lift", "so101", seed=0)
        names = session.controller.joint_names()
        with pytest.raises(DeviceError, match=r"no calibration file .*lerobot-calibrate --robot.type=so101_follower "
                                              rf"--robot.port={arm.port} --robot.id=other"):
            Follower(parse_follower_spec(f"so101_follower:{arm.port}:id=other:calibration={cal}")).open(names)
        arm.write_calibration_file(cal, "off", mismatch=True)
        with pytest.raises(DeviceError, match=r"calibration in .* does not match the servos; calibrate again: lerobot-calibrate .*--robot.id=off"):
            Follower(parse_follower_spec(f"so101_follower:{arm.port}:id=off:calibration={cal}")).open(names)
        assert arm.goal_log() == [] and not any(w["value"] == 1 for w in arm.torque_log())


def test_a_port_where_no_servo_answers_is_one_line(tmp_path: Path):
    with FeetechEmulator.start(tmp_path, role="follower", ids=[]) as bus:
        cal = tmp_path / "cal"
        FeetechEmulator.write_calibration_file(bus, cal, ID)
        started = time.monotonic()
        with pytest.raises(DeviceError, match=rf"^{bus.port}: no servo answered \(ids 1-6\): is the follower powered"):
            Follower(parse_follower_spec(spec_of(bus, cal))).open(("shoulder_pan", "shoulder_lift", "elbow_flex",
                                                                   "wrist_flex", "wrist_roll"))
        assert time.monotonic() - started < 10


def _drive(session: Session, follower: Follower, until, what: str, commands=(), timeout_s: float = 30.0) -> None:
    """Step the session in real time (the follower samples its targets at the control rate) until `until()`."""
    deadline = time.monotonic() + timeout_s
    while not until():
        assert time.monotonic() < deadline, f"timed out waiting for {what}; follower {follower.status()}"
        session.step(list(commands))
        time.sleep(session.dt)


def test_resets_are_followed_at_max_step_with_torque_on_and_an_unplugged_arm_is_shown(tmp_path: Path):
    arm, cal = start_follower(tmp_path)
    with arm:
        session = Session("lift", "so101", seed=0, control_hz=30.0)
        follower = open_follower(spec_of(arm, cal), session)
        try:
            assert follower.status()["state"] in ("connected", "catching up")
            _drive(session, follower, lambda: follower.state == "catching up", "catching up")
            _drive(session, follower, lambda: follower.state == "tracking", "tracking")
            assert "follower: tracking, gap" in follower.line()
            # drive the simulated arm far by joints, then reset to the next seed: the arm is home at once, the
            # follower comes back at max_step
            far = np.array([1.2, -0.8, 0.9, 0.2, 1.5])
            _drive(session, follower, lambda: follower.state == "tracking" and follower.max_gap_deg < 2
                   and abs(follower.targets()[0] - math.degrees(1.2)) < 1, "tracking the far pose", [Command(joints=far)])
            session.reset()  # a new scene: on a loaded machine it may take longer than the whole catch-up below
            session.step([])  # the new scene's first ctrl: the arm's home
            home = follower.targets()
            _drive(session, follower, lambda: follower.state == "tracking" and np.allclose(follower.targets(), home)
                   and follower.max_gap_deg < 2, "tracking after the reset")
            assert not any(w["value"] == 0 for w in arm.torque_log() if w["t"] > goal_rows(arm)[0][0])  # torque stayed on
            assert follower.status()["clamped"] == 0
            # a cable pulled: shown, then the arm is followed again once it answers
            arm.unplug()
            _drive(session, follower, lambda: follower.state == "disconnected", "disconnected")
            assert follower.status()["errors"] >= 1
            arm.replug()
            _drive(session, follower, lambda: follower.state == "tracking", "tracking after the replug")
        finally:
            follower.close()
        goals = assert_eased(arm, FAR)
        # back home from the far pose at max_step after the reset: the pan joint's goals from the last one at the
        # far pose pass through the steps between (69 degrees at 5 a goal: 13 on the way; assert_eased checked
        # each step's size; the emulator's log is whole only now, once the follower let go)
        pan = [g[1] for g in goals]
        far_at = max(range(len(pan)), key=lambda k: (abs(pan[k] - pan[-1]), k))
        back = pan[far_at:]
        on_the_way = {v for v in back if min(back[0], back[-1]) + 2 < v < max(back[0], back[-1]) - 2}
        assert abs(back[0] - back[-1]) > 700 and len(on_the_way) >= 12, back
        assert_torque_off_at_end(arm)
        follower.close()  # again: nothing more happens
        assert follower.status()["state"] == "disconnected"


# --- the joint map (issue 56 item 1) ---------------------------------------------------------------------------

ARM = ("shoulder_pan", "shoulder_lift", "elbow_flex", "wrist_flex", "wrist_roll")


def flipped_map(path: Path, joint: str = "elbow_flex") -> Path:
    """The repository's SO-101 leader map with one joint's sign flipped: an arm whose joint runs backwards."""
    text = builtin_map_path("so101_leader").read_text()
    old = f'{joint} = {{ robot_joint = "{joint}", sign = 1'
    assert old in text
    path.write_text(text.replace(old, f'{joint} = {{ robot_joint = "{joint}", sign = -1'))
    return path


def test_a_leaders_map_with_a_flipped_sign_moves_the_follower_with_the_leader(tmp_path: Path):
    """The leader's map flips elbow_flex: the simulated elbow bends the other way, and the follower (no map of its
    own) maps back through the leader's map, so its Goal_Position moves with the leader's elbow, not against it.
    Leader and follower share one calibration: every goal ends where the leader's servo stands."""
    held = {"shoulder_lift.pos": 20.0, "elbow_flex.pos": 25.0, "wrist_flex.pos": 40.0, "gripper.pos": 50.0}
    arm, cal = start_follower(tmp_path)
    with arm, FeetechEmulator.start(tmp_path, role="leader") as leader:
        leader.write_calibration_file(tmp_path / "lcal", "lead")
        leader.set_action({f"{m}.pos": 0.0 for m in ARM} | held)
        want = leader.positions()
        mid = round(arm.calibration["elbow_flex"].mid)
        assert want[3] - mid > 250  # the leader's elbow is bent 25 degrees up its range
        word = f"so101_leader:{leader.port}:id=lead:calibration={tmp_path / 'lcal'}:map={flipped_map(tmp_path / 'flip.toml')}"
        result = run_cli("run", "--device", word, "--robot", "so101", "--follower", spec_of(arm, cal), "--seconds", "4",
                         "--json", timeout=240)
        assert result.returncode == 0, result.stderr[-3000:]
        assert json.loads(result.stdout)["follower"]["sent"] >= 40
        goals = assert_eased(arm, FAR)
        assert_torque_off_at_end(arm)
    elbow = [g[3] for g in goals]
    assert elbow[-1] - mid > 250, f"the follower's elbow went against the leader's: {elbow[0]} .. {elbow[-1]}, mid {mid}"
    assert max(abs(goals[-1][i] - want[i]) for i in range(1, 7)) <= 8, (goals[-1], want)


def test_the_followers_own_map_comes_first_and_a_missing_one_is_one_line(tmp_path: Path):
    flip = flipped_map(tmp_path / "flip.toml", "wrist_flex")
    names = ARM
    own = parse_follower_spec(f"so101_follower:/dev/ttyACM0:map={flip}")
    assert own.map == flip
    q = np.array([0.1, 0.2, 0.3, 0.4, 0.5])
    built_in = motor_map(parse_follower_spec("so101_follower:/dev/ttyACM0"), names).values(q, 0.5)
    flipped = motor_map(own, names, leader_map=builtin_map_path("so101_leader")).values(q, 0.5)  # its own map first
    assert flipped[3] == pytest.approx(-built_in[3]) and flipped[:3] == pytest.approx(built_in[:3])
    # the leader's map= is found among the --device words, for the arm the follower mirrors (a koch leader's is not)
    words = f"gizmo,so101_leader:/dev/ttyACM1:id=a:map={flip},koch_leader:/dev/ttyACM2:map=/k.toml"
    assert leader_map_of(words) == flip
    assert leader_map_of(f"so101_leader:/dev/ttyACM1:map={flip}:arm=1", arm=0, n_arms=2) is None
    assert leader_map_of("koch_leader:/dev/ttyACM2:map=/k.toml") is None and leader_map_of(None) is None
    # a map= that is not there: one line, exit 2, never the built-in in its place
    result = run_main("run", "--device", "script:x.json", "--robot", "so101",
                      "--follower", f"so101_follower:/dev/ttyACM0:map={tmp_path / 'nope.toml'}")
    assert_one_line_error(result, "nope.toml", "no such joint map file")
    result = run_main("run", "--device", f"so101_leader:{tmp_path / 'ttyNONE'}:map={tmp_path / 'gone.toml'}", "--robot", "so101",
                      "--follower", f"so101_follower:{tmp_path / 'ttyNONE2'}")
    assert_one_line_error(result, "gone.toml", "no such joint map file")


# --- torque off on every way out of connecting (issue 56 item 2) ---------------------------------------------------

STAGES = {  # a stage of Follower.open -> the first packet of it: the emulated cable is pulled as it arrives
    "pinging": "ping",  # the servos' models, before anything is energised
    "reading the calibration": "read",  # the calibration registers
    "configuring": "write",  # inside LeRobot's connect: its first write is torque off, to configure the servos
    "torque on": "sync_read",  # LeRobot's connect returned, torque on: the first read of where the arm stands
}


@pytest.mark.parametrize(("stage", "sig"), [
    ("pinging", signal.SIGTERM), ("reading the calibration", signal.SIGINT), ("configuring", signal.SIGINT),
    ("torque on", signal.SIGINT), ("torque on", signal.SIGTERM),
], ids=["pinging-SIGTERM", "calibration-SIGINT", "configuring-SIGINT", "torque_on-SIGINT", "torque_on-SIGTERM"])
def test_an_interrupt_at_any_stage_of_connecting_leaves_torque_off(tmp_path: Path, stage: str, sig: int):
    """Ctrl-C (SIGINT) or SIGTERM (raised as KeyboardInterrupt, as the command line does) while the follower connects.

    The emulated servos go silent as the host reaches the stage, so the connect is held there (each step asks
    again for seconds), the signal comes, and they answer again. Torque is off on every servo at the end,
    Torque_Enable 0 is the last thing written to each, and nothing follows.
    """
    arm, cal = start_follower(tmp_path)
    main = threading.main_thread().ident
    previous = {s: signal.signal(s, signal.default_int_handler) for s in (signal.SIGINT, signal.SIGTERM)}
    fired = threading.Event()
    opening = threading.Event()

    def interrupt() -> None:
        wait_until(lambda: arm.unplugged() or not opening.is_set(), 60)
        if not opening.is_set():
            return
        time.sleep(0.3)  # the host is asking again inside this stage
        fired.set()
        signal.pthread_kill(main, sig)
        arm.replug()  # the servos hear torque off

    try:
        with arm:
            arm.unplug_at(STAGES[stage])
            opening.set()
            watcher = threading.Thread(target=interrupt, daemon=True)
            watcher.start()
            follower = Follower(parse_follower_spec(spec_of(arm, cal)))
            with pytest.raises(KeyboardInterrupt):
                try:
                    follower.open(ARM)
                finally:
                    opening.clear()
                    watcher.join(30)
            assert fired.is_set() and follower.robot is None
            time.sleep(0.5)  # anything still to be sent would come now
            writes = arm.writes()
            states = {i: arm.read(i, "Torque_Enable") for i in range(1, 7)}
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
    assert states == {i: 0 for i in range(1, 7)}, states
    assert arm.goal_log() == []
    torque = [(k, w) for k, w in enumerate(writes) if w["register"] == "Torque_Enable"]
    enabled = [w for _, w in torque if w["value"] == 1]
    if stage in ("pinging", "reading the calibration"):
        assert not torque, torque  # never energised, nothing written
        return
    last = {w["id"]: w["value"] for _, w in torque}
    assert set(last.values()) == {0}, last  # each servo told: torque off last
    off = max(k for k, w in torque if w["value"] == 0)
    assert [w for w in writes[off + 1:] if w["register"] != "Lock"] == []  # and nothing after (Lock 0 goes with it)
    if stage == "torque on":
        assert {w["id"] for w in enabled} == set(range(1, 7))  # LeRobot's connect had energised every servo
        assert {w["id"] for _, w in torque if w["value"] == 0 and w["t"] >= enabled[-1]["t"]} == set(range(1, 7))


def test_close_waits_for_a_send_or_reconnect_in_flight_and_nothing_follows_torque_off(tmp_path: Path):
    """An unplugged follower is reconnected by its thread (torque on again) while the session ends: close() waits
    for the bus operation in flight, disables torque, and nothing is written after, however long it is watched."""
    arm, cal = start_follower(tmp_path)
    with arm:
        session = Session("lift", "so101", seed=0, control_hz=30.0)
        follower = open_follower(spec_of(arm, cal), session)
        try:
            _drive(session, follower, lambda: len(goal_rows(arm)) >= 5, "goals sent")
            arm.unplug()
            _drive(session, follower, lambda: follower.state == "disconnected", "disconnected")
            arm.replug()
            before = len(arm.torque_log())
            _drive(session, follower, lambda: len(arm.torque_log()) > before, "the reconnect's torque on")  # in flight
        finally:
            follower.close()
        time.sleep(RECONNECT_WATCH_S)
        writes = arm.writes()
        states = {i: arm.read(i, "Torque_Enable") for i in range(1, 7)}
    assert states == {i: 0 for i in range(1, 7)}, states
    last = {w["id"]: w["value"] for w in writes if w["register"] == "Torque_Enable"}
    assert last == {i: 0 for i in range(1, 7)}, last
    off = max(k for k, w in enumerate(writes) if w["register"] == "Torque_Enable" and w["value"] == 0)
    assert [w for w in writes[off + 1:] if w["register"] != "Lock"] == []


RECONNECT_WATCH_S = 2.5  # over two of the follower's reconnect periods (RECONNECT_S)
