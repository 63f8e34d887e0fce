"""LeRobot leader arms as devices (issue 47 items 2 and 5), end to end: `teleop run --device so101_leader:PTY`.

LeRobot's own SOLeader / KochLeader classes, unpatched, talk to byte-level servo emulators on pseudo-terminals
(tests/servo_emulator.py, each in a process of its own); `teleop run` runs in a fresh process as a user would
start it. The emulators' clocks are time.monotonic(); recorded rows carry time.time(): the test converts one to
the other with their difference, read once. Units: radians, metres, seconds; LeRobot's degrees where it says so.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import tempfile
import threading
import time
import tomllib
from pathlib import Path

import mujoco
import numpy as np
import pytest

from devices.base import DeviceError
from devices.joint_map import JointMapError, builtin_map_path, load_joint_map
from devices.leader_connect import LeaderError, parse_leader_spec
from devices.lerobot_leader import make_leader
from devices.registry import KNOWN_DEVICES, DeviceOptions, open_devices
from devices.retarget import Retarget, to_base, to_world
from replay.episode import load_episode
from tests.servo_emulator import MOTOR_NAMES, DynamixelEmulator, FeetechEmulator, from_lerobot
from tests.support import ROOT, assert_one_line_error, popen_cli, run_cli, run_json, wait_until

ARM_JOINTS = MOTOR_NAMES[:5]  # shoulder_pan .. wrist_roll: LeRobot's motor names and the sim so101's joints
WALL_MINUS_MONOTONIC = time.time() - time.monotonic()  # s: recorded wall_time -> the emulators' clock


def leader_word(kind: str, emulator, cal_dir: Path, device_id: str, *options: str) -> str:
    return ":".join([kind, emulator.port, f"id={device_id}", f"calibration={cal_dir}", *options])


def so_motion(emulator, joints, seconds: float, gripper=None, step: float = 0.02) -> dict:
    """A looping emulator motion: joints(t) -> {motor: radians} (LeRobot's degrees on the wire), gripper(t) 0..100."""
    ts = [round(i * step, 6) for i in range(int(round(seconds / step)) + 1)]
    positions: dict[int, list[int]] = {}
    for motor, cal in emulator.calibration.items():
        if motor == "gripper":
            values = [from_lerobot(gripper(t) if gripper else 50.0, cal, "range_0_100") for t in ts]
        else:
            values = [from_lerobot(math.degrees(joints(t).get(motor, 0.0)), cal, "degrees") for t in ts]
        positions[str(cal.id)] = values
    return {"t": ts, "positions": positions, "loop": True}


def so_pose(emulator, **radians: float) -> dict[int, int]:
    """Raw positions of an SO-10x leader held at these joint angles (others 0, gripper 50)."""
    action = {f"{m}.pos": math.degrees(radians.get(m, 0.0)) for m in ARM_JOINTS} | {"gripper.pos": 50.0}
    return emulator.raw_of(action)


class LiveRun:
    """`teleop run ARGS` in a fresh process whose stderr lines the test watches as they come (time.monotonic()):
    forked from the warm process when it may be (tests/warm_cli.py), its stderr a pipe read here, its stdout a file."""

    def __init__(self, *args: str) -> None:
        self._out = tempfile.TemporaryFile()
        read_end, write_end = os.pipe()
        self.proc = popen_cli(["run", *args], self._out, cwd=ROOT, stderr=write_end)
        os.close(write_end)  # the command holds the only write end: its exit ends the reader
        self._stderr = os.fdopen(read_end, "r", errors="replace")
        self.lines: list[tuple[float, str]] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        with self._stderr:
            for line in self._stderr:
                self.lines.append((time.monotonic(), line.rstrip("\n")))

    def wait_line(self, text: str, count: int = 1, timeout_s: float = 60.0) -> float:
        """time.monotonic() when the `count`-th stderr line containing `text` arrived."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            hits = [t for t, line in list(self.lines) if text in line]
            if len(hits) >= count:
                return hits[count - 1]
            assert self.proc.poll() is None or self._reader.is_alive(), f"teleop run ended: {self.stderr()}"
            time.sleep(0.01)
        raise AssertionError(f"no {count} stderr line(s) with {text!r} within {timeout_s} s: {self.stderr()}")

    def finish(self, timeout_s: float = 120.0) -> dict:
        self.proc.wait(timeout_s)
        self._reader.join(5)
        assert self.proc.returncode == 0, f"exit {self.proc.returncode}: {self.stderr()}"
        self._out.seek(0)
        return json.loads(self._out.read())

    def stderr(self) -> str:
        return "\n".join(line for _, line in self.lines)[-3000:]

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def arm_columns(episode, arm: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(monotonic time, qpos, ctrl) of one arm's joints per recorded row."""
    model = episode.build_model()
    joints = episode.meta.arms[arm].joints
    qadr = [model.jnt_qposadr[model.joint(j).id] for j in joints]
    acts = [next(a for a in range(model.nu) if model.actuator_trnid[a, 0] == model.joint(j).id) for j in joints]
    return episode.wall_time - WALL_MINUS_MONOTONIC, episode.qpos[:, qadr], episode.ctrl[:, acts]


def paced_rows(episode, settle_s: float = 0.2, slack_s: float = 0.015) -> np.ndarray:
    """Rows whose last `settle_s` of ticks kept to the wall clock (sim time minus wall time within `slack_s` of its
    median). On a busy machine the loop stalls and then catches up in a burst, stepping the sim ahead on the leader's
    newest (by then old) reading; there the arm cannot be where the leader was at the row's wall time."""
    skew = (episode.wall_time - episode.wall_time[0]) - (episode.time - episode.time[0])
    on_time = np.abs(skew - np.median(skew)) <= slack_s
    ticks = max(1, int(round(settle_s / float(np.median(np.diff(episode.time))))))
    kept = np.array([on_time[max(0, k - ticks):k + 1].all() for k in range(len(on_time))])
    return kept


def base_frame_displacement(episode, arm: int, first: int, last: int) -> np.ndarray:
    """The arm's actual EE displacement from row `first` to row `last`, in the arm's base frame (m)."""
    model = episode.build_model()
    data = mujoco.MjData(model)
    data.qpos[:] = episode.qpos[0]
    mujoco.mj_kinematics(model, data)
    first_joint = model.joint(episode.meta.arms[arm].joints[0]).id
    base = model.body_parentid[model.jnt_bodyid[first_joint]]
    rot = data.xmat[base].reshape(3, 3)
    return rot.T @ (episode.ee_pose[last, arm, :3] - episode.ee_pose[first, arm, :3])


def so101_fk(**q: float) -> np.ndarray:
    """The so101's gripper site position (m, base frame) at these joint angles (radians; others 0)."""
    model = mujoco.MjModel.from_xml_path(str(ROOT / "scenes" / "robots" / "so101.xml"))
    data = mujoco.MjData(model)
    for name, value in q.items():
        data.qpos[model.joint(name).qposadr[0]] = value
    mujoco.mj_kinematics(model, data)
    return data.site_xpos[model.site("ee_site").id].copy()


# -- the so101 driven joint for joint, through an unplug ---------------------------------------------------


@pytest.fixture(scope="module")
def so101_session(tmp_path_factory):
    """A 0.5 Hz, 0.3 rad sine on every leader joint drives the so101 for 8 s; mid-episode the leader is unplugged,
    moved 0.9 rad away on shoulder_pan, and plugged back."""
    tmp = tmp_path_factory.mktemp("so101")
    sine = lambda t: {m: 0.3 * math.sin(math.pi * t) for m in ARM_JOINTS}  # noqa: E731 - 0.5 Hz
    with FeetechEmulator.start(tmp, role="leader") as leader:
        leader.write_calibration_file(tmp / "cal", "arm")
        t_play = leader.play(so_motion(leader, sine, 2.0, gripper=lambda t: 50 + 30 * math.sin(math.pi * t)))
        run = LiveRun("--device", leader_word("so101_leader", leader, tmp / "cal", "arm"), "--robot", "so101", "--scene", "lift",
                      "--seconds", "8", "--record", str(tmp / "rec"), "--json")
        try:
            caught_up = run.wait_line(": connected")  # "easing in" at the first tick (the arm starts at home), then this
            assert any("easing in" in line for _, line in run.lines), run.stderr()
            time.sleep(max(0.0, caught_up + 2.0 - time.monotonic()))  # let it follow for a while (the data the test checks)
            t_unplug = leader.unplug()
            t_lost = run.wait_line(": disconnected")
            time.sleep(max(0.0, t_lost + 0.5 - time.monotonic()))  # unplugged a while: the rows that must hold
            t_moved = leader.set_positions(so_pose(leader, shoulder_pan=0.9))
            t_replug = leader.replug()
            run.wait_line(": connected", count=2)  # the port reopened
            run.wait_line("easing in", count=2)
            summary = run.finish()
        finally:
            run.kill()
    return {"summary": summary, "stderr": run.stderr(), "t_play": t_play, "caught_up": caught_up, "t_unplug": t_unplug,
            "t_lost": t_lost, "t_moved": t_moved, "t_replug": t_replug}


@pytest.mark.e2e
def test_so101_leader_drives_the_so101_joint_for_joint(so101_session):
    """After the ease-in the sim's joints follow the leader's within 0.05 rad (at the lag that fits best, <= 0.25 s:
    the reads of six servos over a pseudo-terminal come late on a loaded machine; bench/leader.py measures the lag)."""
    s = so101_session
    episode = load_episode(s["summary"]["files"][0])
    t, qpos, _ = arm_columns(episode)
    window = (t > s["caught_up"] + 0.3) & (t < s["t_unplug"]) & paced_rows(episode)
    assert window.sum() >= 20, f"only {window.sum()} rows kept to the clock between the ease-in and the unplug"
    errors = []
    lags = np.arange(0.0, 0.251, 0.01)
    for lag in lags:
        leader = 0.3 * np.sin(math.pi * (t[window] - lag - s["t_play"]))
        errors.append(float(np.max(np.abs(qpos[window] - leader[:, None]))))
    assert min(errors) < 0.05, f"max |sim - leader| per lag 0..0.25 s: {np.round(errors, 3)}"
    assert np.ptp(qpos[window], axis=0).min() > 0.3, "the arm did not move with the leader"
    # the gripper: LeRobot's 0..100 (here 50 +- 30) -> opening 0..1 -> ctrl 0 (closed) .. 0.55 (open, robot.py)
    gripper_ctrl = episode.ctrl[window, episode.build_model().actuator("gripper").id]
    misses = [np.max(np.abs(gripper_ctrl - 0.55 * (0.5 + 0.3 * np.sin(math.pi * (t[window] - lag - s["t_play"])))))
              for lag in lags]
    assert min(misses) < 0.02, f"max |gripper ctrl - leader's| per lag: {np.round(misses, 3)}"


@pytest.mark.e2e
def test_an_unplugged_leader_holds_the_arm_and_eases_in_on_return(so101_session):
    s = so101_session
    assert "disconnected" in s["stderr"] and s["stderr"].count("easing in") >= 2, s["stderr"]
    episode = load_episode(s["summary"]["files"][0])
    t, qpos, ctrl = arm_columns(episode)
    held = (t > s["t_lost"]) & (t < s["t_replug"])
    assert held.sum() >= 3, f"only {held.sum()} rows while unplugged"
    assert np.ptp(ctrl[held], axis=0).max() == 0.0, "the arm's targets moved while the leader was unplugged"
    after = t > s["t_replug"]
    pan = ctrl[after, 0]
    assert np.max(np.abs(np.diff(pan))) <= 0.05 + 1e-9, "the arm jumped to the leader instead of easing in"
    assert abs(qpos[-1, 0] - 0.9) < 0.03 and abs(pan[-1] - 0.9) < 0.01, (qpos[-1], pan[-1])


@pytest.mark.e2e
def test_the_leader_episode_is_saved_and_replays_bit_exact(so101_session):
    summary = so101_session["summary"]
    assert summary["devices"] == [summary["devices"][0]] and summary["devices"][0].startswith("so101_leader:")
    assert summary["sim_seconds"] == pytest.approx(8.0) and len(summary["files"]) == 1
    verify = run_json("replay", summary["files"][0], "--verify", "--json")
    assert verify["bit_exact"] is True, verify


# -- retargeting onto other robots ---------------------------------------------------------------------------


FORWARD = {"shoulder_lift": 0.3, "elbow_flex": -0.3}  # the leader's gripper forward and a little down, not turned


def ramp(pose: dict[str, float], hold_s: float = 0.6, move_s: float = 1.0):
    """Joint angles at rest for `hold_s`, then moving linearly to `pose` over `move_s`, then held."""
    def at(t: float) -> dict[str, float]:
        share = min(max((t - hold_s) / move_s, 0.0), 1.0)
        return {m: share * v for m, v in pose.items()}
    return at


@pytest.mark.e2e
def test_an_so101_leader_drives_the_panda_by_retargeting(tmp_path):
    """Pushing the leader's gripper forward moves the Panda's EE forward (+x, base frame) by scale x as much."""
    with FeetechEmulator.start(tmp_path, role="leader") as leader:
        leader.write_calibration_file(tmp_path / "cal", "arm")
        run = LiveRun("--device", leader_word("so101_leader", leader, tmp_path / "cal", "arm", "scale=1.5"),
                      "--robot", "panda", "--scene", "lift", "--seconds", "4", "--record", str(tmp_path / "rec"), "--json")
        try:
            run.wait_line(": connected")
            leader.play({**so_motion(leader, ramp(FORWARD), 2.0), "loop": False})
            summary = run.finish()
        finally:
            run.kill()
    moved = so101_fk(**FORWARD) - so101_fk()
    assert moved[0] > 0.025, moved
    episode = load_episode(summary["files"][0])
    got = base_frame_displacement(episode, 0, 0, episode.steps - 1)
    assert np.linalg.norm(got - 1.5 * moved) < 0.01, f"panda moved {got}, expected 1.5 x {moved}"


@pytest.mark.e2e
def test_two_leaders_drive_the_two_arms_of_the_bimanual_rig(tmp_path):
    """arm=0 and arm=1: each arm's EE moves as its own leader's gripper does (forward; sideways), scaled by the reach ratio."""
    sideways = {"shoulder_pan": 0.15}
    with FeetechEmulator.start(tmp_path, role="leader") as left, FeetechEmulator.start(tmp_path, role="leader") as right:
        left.write_calibration_file(tmp_path / "cal", "left")
        right.write_calibration_file(tmp_path / "cal", "right")
        words = [leader_word("so101_leader", left, tmp_path / "cal", "left", "arm=0"),
                 leader_word("so101_leader", right, tmp_path / "cal", "right", "arm=1")]
        run = LiveRun("--device", ",".join(words), "--robot", "bimanual", "--scene", "lift", "--seconds", "4",
                      "--record", str(tmp_path / "rec"), "--json")
        try:
            run.wait_line(": connected", count=2)
            left.play({**so_motion(left, ramp(FORWARD), 2.0), "loop": False})
            right.play({**so_motion(right, ramp(sideways), 2.0), "loop": False})
            summary = run.finish()
        finally:
            run.kill()
    scale = 0.75 / 0.43  # the bimanual arm's reach over the so101's (scenes/assembly/robot.py)
    episode = load_episode(summary["files"][0])
    for arm, pose in ((0, FORWARD), (1, sideways)):
        want = scale * (so101_fk(**pose) - so101_fk())
        got = base_frame_displacement(episode, arm, 0, episode.steps - 1)
        assert np.linalg.norm(got - want) < 0.015, f"arm {arm} moved {got}, expected {want}"


@pytest.mark.e2e
def test_a_retargeting_leader_back_from_an_unplug_eases_the_panda_in(tmp_path):
    """In process (a real Session, LeRobot's SOLeader on the emulator): unplugged, the Panda's target holds; the
    leader moved meanwhile and plugged back, the target moves toward it at most 1 cm a tick, then follows."""
    from teleop.control.session import Session

    session = Session(scene="lift", robot="panda", seed=0, control_hz=30.0)
    view = session.controller
    with FeetechEmulator.start(tmp_path, role="leader") as leader:
        leader.write_calibration_file(tmp_path / "cal", "arm")
        device = make_leader("so101_leader", f"{leader.port}:id=arm:calibration={tmp_path / 'cal'}:scale=2", log=lambda m: None)
        device.start()
        try:
            assert device.choose_mode(view) == "retarget" and device.mode == "retarget"
            for _ in range(5):
                session.step(device.poll(view, session.dt))
            start = view.target_pose(0)[0]
            leader.unplug()
            wait_until(lambda: device.status() == "disconnected", 10, "the device to see the unplug")
            for _ in range(5):
                assert device.poll(view, session.dt) == []
                session.step([])
            assert np.allclose(view.target_pose(0)[0], start), "the target moved while unplugged"
            leader.set_positions(so_pose(leader, **FORWARD))
            leader.replug()
            wait_until(lambda: device.status() == "connected", 10, "the device to reconnect")
            path, said = [start], []
            for _ in range(40):
                session.step(device.poll(view, session.dt))
                path.append(view.target_pose(0)[0])
                said.append(device.status())
        finally:
            device.close()
    steps = np.linalg.norm(np.diff(path, axis=0), axis=1)
    want = 2.0 * (so101_fk(**FORWARD) - so101_fk())  # the Panda's base frame is the world's
    assert said[0] == "easing in" and said[-1] == "connected", said
    assert steps.max() <= 0.01 + 1e-9 and steps[:3].min() > 0.0099, steps.round(4)
    assert np.linalg.norm(path[-1] - (start + want)) < 1e-3, (path[-1] - start, want)  # 1 mm: the leader's raw steps


PRESSED = {"shoulder_lift": 1.4, "elbow_flex": 0.2, "wrist_flex": 1.2}  # the so101's gripper pushed down into the table


@pytest.mark.e2e
def test_re_engaging_an_arm_pressed_on_the_table_eases_from_its_targets(tmp_path):
    """Issue 56 item 4. In process (a real Session, LeRobot's SOLeader on the emulator): the leader presses the so101
    into the table, so its joint targets lie far past where the joints stand; unplugged, the leader is moved to where
    the joints stand (within 0.5 rad of them, over 0.5 rad from the targets) and plugged back. The ease-in decides
    with the targets it eases from: no joint target steps more than 0.05 rad a tick on the way to the leader."""
    from teleop.control.session import Session

    session = Session(scene="lift", robot="so101", seed=0, control_hz=30.0)
    view = session.controller
    with FeetechEmulator.start(tmp_path, role="leader") as leader:
        leader.write_calibration_file(tmp_path / "cal", "arm")
        leader.set_positions(so_pose(leader, **PRESSED))
        device = make_leader("so101_leader", f"{leader.port}:id=arm:calibration={tmp_path / 'cal'}", log=lambda m: None)
        device.start()
        try:
            assert device.choose_mode(view) == "joints"
            for _ in range(80):  # eased in from home (shoulder_lift 1.25 rad away: 25 ticks), then pressing
                session.step(device.poll(view, session.dt))
            pressed = view.joint_targets(0).copy()
            standing = view.joint_positions(0).copy()
            lift = ARM_JOINTS.index("shoulder_lift")
            assert abs(pressed[lift] - PRESSED["shoulder_lift"]) < 0.01, pressed
            assert pressed[lift] - standing[lift] > 0.6, "the arm is not held up by the table"
            leader.unplug()
            wait_until(lambda: device.status() == "disconnected", 10, "the device to see the unplug")
            for _ in range(3):
                session.step(device.poll(view, session.dt))
            leader.set_positions(so_pose(leader, **dict(zip(ARM_JOINTS, map(float, standing)))))
            leader.replug()
            wait_until(lambda: device.status() == "connected", 10, "the device to reconnect")
            path, said = [view.joint_targets(0).copy()], []
            for _ in range(60):
                session.step(device.poll(view, session.dt))
                path.append(view.joint_targets(0).copy())
                said.append(device.status())
        finally:
            device.close()
    assert np.allclose(path[0], pressed), "the targets moved while the leader was unplugged"
    steps = np.abs(np.diff(np.array(path), axis=0))
    assert steps.max() <= 0.05 + 1e-9, f"a joint target jumped {steps.max():.3f} rad in one tick"
    assert said[0] == "easing in" and said[-1] == "connected", said
    assert np.max(np.abs(path[-1] - standing)) < 0.01, (path[-1], standing)  # it reached the leader (a raw step: 1.5 mrad)


# -- Koch: joint space only ----------------------------------------------------------------------------------


@pytest.mark.e2e
def test_a_koch_leader_drives_the_so101_in_joint_space_easing_in_at_every_episode(tmp_path):
    """LeRobot's -100..100 readings become radians through the repository's koch map (at -100 and at +100); each
    of two episodes starts at home and eases in (at most 0.05 rad a tick) rather than jumping to the leader."""
    held = {"shoulder_pan": 10.0, "shoulder_lift": 20.0, "elbow_flex": -15.0, "wrist_flex": 10.0, "wrist_roll": 0.0}
    table = tomllib.loads((ROOT / "devices" / "leader_maps" / "koch_leader.toml").read_text())["joints"]
    want = np.array([table[m]["at_minus_100"] + (held[m] + 100) / 200 * (table[m]["at_plus_100"] - table[m]["at_minus_100"])
                     for m in ARM_JOINTS])
    with DynamixelEmulator.start(tmp_path, role="leader") as leader:
        leader.write_calibration_file(tmp_path / "cal", "koch")
        leader.set_action({f"{m}.pos": v for m, v in held.items()} | {"gripper.pos": 50.0})
        summary = run_json("run", "--device", leader_word("koch_leader", leader, tmp_path / "cal", "koch"), "--robot", "so101",
                           "--scene", "lift", "--seconds", "2.5", "--episodes", "2", "--record", str(tmp_path / "rec"), "--json")
    # 2.5 s, 75 ticks: the wrist's ease-in takes 27, and a loaded machine may hold a few readings back
    assert len(summary["files"]) == 2
    home = np.array([0.0, 0.1511, -0.0935, 1.5132, 0.0])  # the so101's home (scenes/assembly/robot.py)
    step = 2 * math.pi / 4095 * 1.01  # one raw step of a full-turn joint, the coarsest here
    for path in summary["files"]:
        _, qpos, ctrl = arm_columns(load_episode(path))
        moves = np.abs(np.diff(np.vstack([home, ctrl]), axis=0))
        assert moves.max() <= 0.05 + 1e-9 and moves[:5].max() > 0.049, f"{path}: not an ease-in: {moves[:5].round(3)}"
        assert np.max(np.abs(ctrl[-1] - want)) < step, (ctrl[-1], want)
        assert np.max(np.abs(qpos[-1] - want)) < 0.03, (qpos[-1], want)


# -- faults: one line on stderr, exit 2, nothing recorded -----------------------------------------------------


@pytest.mark.e2e
def test_every_leader_fault_is_one_line_and_exit_2(tmp_path):
    """A missing port, no servo answering, a wrong servo model, no calibration file, a mismatched one, and a koch
    leader on the Panda: each stops `teleop run` with one line and exit 2 before anything is recorded."""
    with (FeetechEmulator.start(tmp_path / "ok", role="leader") as good,
          FeetechEmulator.start(tmp_path / "none", ids=[], role="leader") as empty,
          FeetechEmulator.start(tmp_path / "wrong", model=1284, role="leader") as wrong,
          DynamixelEmulator.start(tmp_path / "koch", role="leader") as koch):
        good.write_calibration_file(tmp_path / "cal", "arm")
        good.write_calibration_file(tmp_path / "bad", "arm", mismatch=True)
        wrong.write_calibration_file(tmp_path / "wcal", "arm")
        koch.write_calibration_file(tmp_path / "kcal", "koch")
        (tmp_path / "empty").mkdir()
        cases = {
            "missing port": ("so101_leader:/dev/serial/by-id/usb-no-such-leader-if00", "so101", ["no such serial port", "usb-no-such"]),
            "no servo": (f"so101_leader:{empty.port}:id=arm:calibration={tmp_path / 'cal'}", "so101", ["no servo answered"]),
            "wrong model": (f"so101_leader:{wrong.port}:id=arm:calibration={tmp_path / 'wcal'}", "so101",
                            ["wrong servo model", "1284"]),
            "no calibration": (f"so101_leader:{good.port}:id=arm:calibration={tmp_path / 'empty'}", "so101",
                               ["no calibration file", f"lerobot-calibrate --teleop.type=so101_leader --teleop.port={good.port} "
                                                       "--teleop.id=arm"]),
            "mismatched calibration": (f"so101_leader:{good.port}:id=arm:calibration={tmp_path / 'bad'}", "so101",
                                       ["does not match", "lerobot-calibrate --teleop.type=so101_leader"]),
            "koch on the panda": (f"koch_leader:{koch.port}:id=koch:calibration={tmp_path / 'kcal'}", "panda",
                                  ["joint for joint only", "--robot so101"]),
        }
        def run(i: int, word: str, robot: str) -> subprocess.CompletedProcess:
            return run_cli("run", "--device", word, "--robot", robot, "--scene", "lift", "--seconds", "1",
                           "--record", str(tmp_path / f"rec{i}"), timeout=180)

        # One after another (two of them share the good emulator's port; six at once also loaded the machine enough
        # to make other tests' servo replies late)
        results = {name: run(i, word, robot) for i, (name, (word, robot, _)) in enumerate(cases.items())}
    for name, result in results.items():
        try:
            assert_one_line_error(result, *cases[name][2])
        except AssertionError as exc:
            raise AssertionError(f"{name}: {exc}") from None
    recorded = sorted(str(p) for p in tmp_path.glob("rec*/*") if p.suffix in (".mcap", ".h5", ".hdf5"))
    assert not recorded, recorded


# -- in process: spec words, joint maps, retargeting arithmetic -----------------------------------------------


@pytest.mark.unit
def test_leader_words_keep_their_case_and_ports_may_hold_colons():
    port = "/dev/serial/by-path/pci-0000:00:14.0-usb-0:1:1.0"
    spec = parse_leader_spec("so101_leader", f"{port}:id=LeftArm:calibration=/Cal/Dir:map=/Maps/Mine.toml:Scale=1.5:arm=1", 2)
    assert (spec.port, spec.id, str(spec.calibration), str(spec.map), spec.scale, spec.arm) == \
        (port, "LeftArm", "/Cal/Dir", "/Maps/Mine.toml", 1.5, 1)
    assert {"so101_leader", "so100_leader", "koch_leader"} <= set(KNOWN_DEVICES)
    device = make_leader("koch_leader", "/dev/ttyACM0:id=K")
    assert (device.name, device.kind, device.map.robot, device.status()) == ("koch_leader:/dev/ttyACM0", "koch_leader", "so101", "disconnected")
    for arg, needle in (("", "needs its serial port"), ("/dev/ttyACM0:arm=2", "arm=2"), ("/dev/ttyACM0:speed=3", "unknown option 'speed'"),
                        ("/dev/ttyACM0:scale=0", "scale= must be a positive number"), ("/dev/ttyACM0:id=a:id=b", "given twice")):
        with pytest.raises(LeaderError, match=needle):
            parse_leader_spec("so101_leader", arg, 2)


@pytest.mark.unit
def test_a_leader_that_cannot_start_stops_open_devices(tmp_path):
    """Other devices that fail are listed and skipped; a leader arm raises (the command stops: one line, exit 2)."""
    with pytest.raises(LeaderError, match="no such serial port"):
        open_devices(f"gizmo,so101_leader:{tmp_path / 'ttyACM7'}", DeviceOptions(), require_any=False)
    started, problems = open_devices("gizmo,spacemouse:3", DeviceOptions(), require_any=False)
    assert [d.name for d in started] == ["gizmo"] and len(problems) == 1 and problems[0].startswith("spacemouse:3")


@pytest.mark.unit
def test_the_repository_maps_load_and_map_lerobots_zero_to_the_sims():
    for kind in ("so101_leader", "so100_leader", "koch_leader"):
        jmap = load_joint_map(builtin_map_path(kind))
        assert jmap.robot == "so101" and [r.robot for r in jmap.joints] == list(ARM_JOINTS) and jmap.gripper is not None
    so = load_joint_map(builtin_map_path("so101_leader"))
    zero = {m: 0.0 for m in MOTOR_NAMES}
    assert so.robot_joints(zero) == {m: 0.0 for m in ARM_JOINTS}
    assert so.robot_joints({**zero, "elbow_flex": 90.0})["elbow_flex"] == pytest.approx(math.pi / 2)
    assert [so.gripper_opening({**zero, "gripper": g}) for g in (-5.0, 0.0, 25.0, 100.0, 120.0)] == [0.0, 0.0, 0.25, 1.0, 1.0]
    koch = load_joint_map(builtin_map_path("koch_leader"))
    assert koch.robot_joints({**zero, "shoulder_lift": -100.0})["shoulder_lift"] == pytest.approx(-1.74533)
    assert koch.robot_joints({**zero, "shoulder_lift": 100.0})["shoulder_lift"] == pytest.approx(1.74533)


@pytest.mark.unit
def test_a_bad_map_is_one_line_naming_the_file_and_the_key(tmp_path):
    good = builtin_map_path("so101_leader").read_text()
    cases = {
        "typo": (good.replace('elbow_flex = { robot_joint = "elbow_flex", sign = 1', 'elbow_flex = { robot_joint = "elbow_flex", sing = 1'),
                 "joints.elbow_flex.sing"),
        "sign": (good.replace('wrist_flex = { robot_joint = "wrist_flex", sign = 1', 'wrist_flex = { robot_joint = "wrist_flex", sign = 2'),
                 "joints.wrist_flex.sign"),
        "twice": (good.replace('robot_joint = "wrist_roll"', 'robot_joint = "wrist_flex"'), "'wrist_flex' is driven by more than one"),
        "toml": (good + "\n[joints\n", "not valid TOML"),
        "units": (good.replace('units = "degrees"', 'units = "radians"'), "units must be one of"),
        "gripper": (good.replace("open = 100.0", "open = 0.0"), "gripper.closed and gripper.open must differ"),
    }
    for name, (text, needle) in cases.items():
        path = tmp_path / f"{name}.toml"
        path.write_text(text)
        with pytest.raises(JointMapError) as caught:
            load_joint_map(path)
        message = str(caught.value)
        assert str(path) in message and needle in message and "\n" not in message, (name, message)
    with pytest.raises(DeviceError, match="units = 'degrees', but LeRobot reads a koch_leader in 'range'"):
        make_leader("koch_leader", f"/dev/ttyACM0:map={builtin_map_path('so101_leader')}")


@pytest.mark.unit
def test_retargeting_moves_the_robot_by_scale_times_the_leaders_motion():
    base_pos, base_quat = np.array([0.42, 0.0, 0.0]), np.array([0.0, 0.0, 0.0, 1.0])  # yawed by pi, as the rig's right arm
    world = (np.array([0.1, 0.2, 0.3]), np.array([0.5, 0.5, 0.5, 0.5]))
    local = to_base(base_pos, base_quat, *world)
    assert np.allclose(local[0], [0.32, -0.2, 0.3]) and all(np.allclose(a, b) for a, b in zip(to_world(base_pos, base_quat, *local), world))
    r = Retarget(scale=2.0)
    r.engage((np.array([0.3, 0.0, 0.2]), np.array([1.0, 0, 0, 0])), local)
    turn = np.array([math.cos(0.1), 0.0, 0.0, math.sin(0.1)])  # 0.2 rad about the base's z
    pos, quat = r.target((np.array([0.33, 0.01, 0.2]), turn))
    assert np.allclose(pos, local[0] + 2.0 * np.array([0.03, 0.01, 0.0]))
    expect = np.empty(4)
    mujoco.mju_mulQuat(expect, turn, local[1])
    assert np.allclose(quat, expect)
