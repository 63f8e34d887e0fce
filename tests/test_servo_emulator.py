"""LeRobot's real leader, follower and motor-bus classes, unpatched, against the byte-level servo emulators.

What these establish about LeRobot 0.6 (the leader device, the follower and `teleop devices` rely on it):
- `connect(calibrate=False)` with a calibration file that matches the registers: `is_calibrated` True;
  one range off: False (and connect does not prompt).
- A pulled cable: `get_action()` raises ConnectionError ("Failed to sync read 'Present_Position' ...
  There is no status packet!"); once the cable is back the same connected object reads again, no reconnect.
  `disconnect()` meanwhile raises ConnectionError on its Torque_Enable write and leaves the port open.
- A USB adapter pulled out (the pty closed): the first `get_action()` raises termios.error (EIO, not a
  ConnectionError), the next ones ConnectionError "Port is in use!"; `disconnect()` raises termios.error.
- A servo of another model: `connect()` raises RuntimeError ("FeetechMotorsBus motor check failed on
  port ...", listing expected and found model numbers); no servo at all: the same, "Missing motor IDs".
- `SOFollower.send_action` with max_relative_target (a float: an int raises TypeError) clamps each joint
  against the present position it reads first; `disconnect()` writes Torque_Enable 0 to every servo.
"""

from __future__ import annotations

import json
import os
import signal
import statistics
import subprocess
import sys
import time

import pytest

from tests.servo_emulator import (
    KOCH_CALIBRATION,
    MOTOR_NAMES,
    SO101_CALIBRATION,
    SO_DEGREES,
    DynamixelEmulator,
    FeetechEmulator,
    connect_device,
    read_retrying,
    from_lerobot,
    step_of,
    to_lerobot,
)
from tests.servo_wire import DynamixelBus, FeetechBus
from tests.support import ROOT, wait_until

pytestmark = pytest.mark.e2e



def so_leader(arm: FeetechEmulator, tmp_path, device_id: str = "leader"):
    from lerobot.teleoperators.so_leader import SOLeader, SOLeaderTeleopConfig

    return SOLeader(SOLeaderTeleopConfig(port=arm.port, id=device_id, calibration_dir=tmp_path / "cal", use_degrees=True))


def so_follower(arm: FeetechEmulator, tmp_path, max_relative_target=None, device_id: str = "follower"):
    from lerobot.robots.so_follower import SOFollower, SOFollowerRobotConfig

    config = SOFollowerRobotConfig(port=arm.port, id=device_id, calibration_dir=tmp_path / "cal",
                                   max_relative_target=max_relative_target, use_degrees=True)
    return SOFollower(config)


# -- the bytes themselves ---------------------------------------------------------------------------------------


def test_checksums_match_the_published_examples_and_the_sdks():
    from dynamixel_sdk import PacketHandler

    # ROBOTIS' protocol 2.0 manual: PING to id 1 is FF FF FD 00 01 03 00 01 19 4E.
    assert DynamixelBus.crc(bytes.fromhex("FFFFFD0001030001")) == 0x4E19
    packet = bytes(range(200))
    assert DynamixelBus.crc(packet) == PacketHandler(2.0).updateCRC(0, list(packet), len(packet))
    # Feetech: READ id 1, address 56, 2 bytes -> checksum ~(1 + 4 + 2 + 56 + 2)
    assert FeetechBus.checksum(bytes([1, 4, 2, 56, 2])) == (~65) & 0xFF


def test_raw_and_lerobot_units_round_trip_within_a_step():
    for motor in MOTOR_NAMES:
        cal, mode = SO101_CALIBRATION[motor], SO_DEGREES.mode(motor)
        for value in ((-30.0, 0.0, 20.0, 45.5) if mode == "degrees" else (0.0, 37.5, 100.0)):
            raw = from_lerobot(value, cal, mode)
            assert abs(to_lerobot(raw, cal, mode) - value) <= 0.5 * step_of(cal, mode) + 1e-9
    elbow = KOCH_CALIBRATION["elbow_flex"]  # drive mode 1: Feetech's bus would flip it, Dynamixel's does not
    assert to_lerobot(elbow.range_max, elbow, "m100_100", apply_drive_mode=False) == 100
    assert to_lerobot(elbow.range_max, elbow, "m100_100", apply_drive_mode=True) == -100


# -- SO-101 leader -------------------------------------------------------------------------------------------


def test_so_leader_connects_calibrated_and_reads_the_motion_then_a_step(tmp_path):
    with FeetechEmulator.start(tmp_path, role="leader") as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader")
        leader = so_leader(arm, tmp_path)
        connect_device(leader)
        try:
            assert leader.is_calibrated
            # elbow ramps 0 -> +30 degrees over 3 s, held there; the gripper closes 0 -> 100 % meanwhile
            elbow, grip = SO101_CALIBRATION["elbow_flex"], SO101_CALIBRATION["gripper"]
            ramp = {"t": [0.0, 3.0], "loop": False, "positions": {
                3: [from_lerobot(0, elbow, "degrees"), from_lerobot(30, elbow, "degrees")],
                6: [grip.range_min, grip.range_max]}}
            start = arm.play(ramp)
            for _ in range(5):
                before = time.monotonic() - start
                action = leader.get_action()
                after = time.monotonic() - start
                assert set(action) == {f"{m}.pos" for m in MOTOR_NAMES}
                low, high = 30 * min(before, 3) / 3, 30 * min(after, 3) / 3
                step = arm.tolerance("elbow_flex")
                assert low - step <= action["elbow_flex.pos"] <= high + step, (before, after, action)
                assert 100 * min(before, 3) / 3 - 1 <= action["gripper.pos"] <= 100 * min(after, 3) / 3 + 1
                assert abs(action["shoulder_pan.pos"]) <= arm.tolerance("shoulder_pan")
                time.sleep(0.05)
            # a step by hand shows in the very next read
            changed_at = arm.set_action({"elbow_flex.pos": -20.0, "wrist_roll.pos": 90.0})
            assert changed_at <= time.monotonic()
            action = leader.get_action()
            assert action["elbow_flex.pos"] == pytest.approx(-20.0, abs=arm.tolerance("elbow_flex"))
            assert action["wrist_roll.pos"] == pytest.approx(90.0, abs=arm.tolerance("wrist_roll"))
            assert arm.action_of(arm.positions())["elbow_flex.pos"] == pytest.approx(action["elbow_flex.pos"])
        finally:
            leader.disconnect()
        assert not leader.is_connected


def test_a_calibration_file_that_does_not_match_the_servos_is_reported_not_calibrated(tmp_path):
    with FeetechEmulator.start(tmp_path) as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader", mismatch=True)
        leader = so_leader(arm, tmp_path)
        connect_device(leader)  # no prompt: calibrate() is the one that would wait on input()
        try:
            assert leader.is_calibrated is False
        finally:
            leader.disconnect()


def test_unplugged_leader_raises_connection_error_and_reads_again_once_replugged(tmp_path):
    with FeetechEmulator.start(tmp_path) as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader")
        leader = so_leader(arm, tmp_path)
        connect_device(leader)
        try:
            assert leader.get_action()
            arm.unplug()
            with pytest.raises(ConnectionError, match="Failed to sync read 'Present_Position'.*There is no status packet"):
                leader.get_action()
            assert leader.is_connected  # the port is still open: only the servos went quiet
            arm.replug()
            arm.set_action({"shoulder_lift.pos": 12.0})
            assert leader.get_action()["shoulder_lift.pos"] == pytest.approx(12.0, abs=arm.tolerance("shoulder_lift"))
            # one servo gone: the same error names all ids; a corrupted packet is retried (num_read_retries=2)
            arm.unplug(ids=[4])
            with pytest.raises(ConnectionError):
                leader.get_action()
            arm.replug(ids=[4])
            arm.corrupt(1)
            assert leader.get_action()["shoulder_lift.pos"] == pytest.approx(12.0, abs=arm.tolerance("shoulder_lift"))
            # disconnecting from quiet servos fails on its torque-off write and leaves the port open
            arm.unplug()
            with pytest.raises(ConnectionError, match="Failed to write 'Torque_Enable' on id_=1 with '0' after 6 tries"):
                leader.disconnect()
            assert leader.is_connected
            arm.replug()
        finally:
            leader.disconnect()
        assert not leader.is_connected and len([t for t in arm.torque_log() if t["value"] == 0]) >= 6


def test_a_vanished_usb_adapter_raises_termios_error_first_then_connection_error(tmp_path):
    """The pty closed under LeRobot (as a USB adapter pulled out): not a ConnectionError the first time."""
    import termios

    with FeetechEmulator.start(tmp_path) as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader")
        leader = so_leader(arm, tmp_path)
        connect_device(leader)
        arm.vanish()
        assert not os.path.exists(arm.port)
        with pytest.raises(termios.error):  # pyserial's flush (tcdrain) before the packet: EIO
            leader.get_action()
        with pytest.raises(ConnectionError, match="Port is in use"):  # the SDK's busy flag was left set
            leader.get_action()
        with pytest.raises(termios.error):
            leader.disconnect()
        leader.bus.port_handler.closePort()
        again = so_leader(arm, tmp_path)
        with pytest.raises(ConnectionError, match="Could not connect on port"):
            again.connect(calibrate=False)


def test_a_servo_of_another_model_or_none_at_all_fails_connect_with_runtime_error(tmp_path):
    with FeetechEmulator.start(tmp_path, model={1: 777, 2: 777, 3: 2825, 4: 777, 5: 777, 6: 777}) as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader")
        leader = so_leader(arm, tmp_path)
        with pytest.raises(RuntimeError, match=r"motor check failed on port(.|\n)*3 \(elbow_flex\): expected 777, found 2825"):
            leader.connect(calibrate=False)
        assert leader.is_connected  # LeRobot leaves the port open after a failed handshake
        leader.bus.port_handler.closePort()
    with FeetechEmulator.start(tmp_path, ids=[]) as empty:
        leader = so_leader(empty, tmp_path)
        with pytest.raises(RuntimeError, match="Missing motor IDs"):
            leader.connect(calibrate=False)
        leader.bus.port_handler.closePort()


def test_median_sync_read_of_six_servos(tmp_path):
    with FeetechEmulator.start(tmp_path) as arm:
        arm.write_calibration_file(tmp_path / "cal", "leader")
        leader = so_leader(arm, tmp_path)
        connect_device(leader)
        try:
            times = []
            for _ in range(300):
                start = time.perf_counter()
                leader.get_action()
                times.append(time.perf_counter() - start)
        finally:
            leader.disconnect()
    print(f"\nSOLeader.get_action (6-servo sync read) on the emulator: median {statistics.median(times) * 1e3:.2f} ms, "
          f"max {max(times) * 1e3:.2f} ms over {len(times)}")
    assert arm.stats  # the figure is printed, not asserted: it depends on the machine's load


# -- SO-101 follower -----------------------------------------------------------------------------------------


def test_so_follower_clamps_each_step_and_disables_torque_on_disconnect(tmp_path):
    with FeetechEmulator.start(tmp_path, role="follower", rate=None) as arm:
        arm.write_calibration_file(tmp_path / "cal", "follower")
        from lerobot.robots.utils import ensure_safe_goal_position

        with pytest.raises(TypeError):  # LeRobot's clamp takes a float or a dict: max_relative_target=5 fails at send_action
            ensure_safe_goal_position({"elbow_flex": (1.0, 0.0)}, 5)
        robot = so_follower(arm, tmp_path, max_relative_target=5.0)
        connect_device(robot)
        assert robot.is_calibrated
        enabled = {w["id"] for w in arm.torque_log() if w["value"] == 1}
        assert enabled == set(range(1, 7)), "configure() re-enables torque after writing its settings"
        first = len(arm.goal_log())
        target = {f"{m}.pos": 0.0 for m in MOTOR_NAMES} | {"elbow_flex.pos": 20.0, "gripper.pos": 50.0}
        sent = [robot.send_action(target) for _ in range(5)]
        elbow = [s["elbow_flex.pos"] for s in sent]
        # each step is 5 degrees from the position read back, which LeRobot's int() truncation leaves up to a raw
        # step short of the last goal: 5, 9.92, 14.85, 19.77, then the target itself
        assert elbow[0] == pytest.approx(5.0) and elbow[-1] == pytest.approx(20.0)
        assert all(0 < b - a <= 5.0 + 1e-9 for a, b in zip(elbow, elbow[1:]))
        obs = robot.get_observation()  # answered after the emulator has taken every earlier (unanswered) sync write
        goals = [g for g in arm.goal_log()[first:] if g["motor"] == "elbow_flex"]
        assert len(goals) == 5 and all(g["via"] == "sync_write" for g in goals)
        degrees = [arm.action_of({3: g["value"]})["elbow_flex.pos"] for g in goals]
        assert degrees == pytest.approx(elbow, abs=arm.tolerance("elbow_flex"))
        assert all(b - a <= 5.0 + arm.tolerance("elbow_flex") for a, b in zip([0.0] + degrees, degrees))
        assert obs["elbow_flex.pos"] == pytest.approx(20.0, abs=2 * arm.tolerance("elbow_flex"))
        before = time.monotonic()
        robot.disconnect()
        off = {w["id"] for w in arm.torque_log() if w["value"] == 0 and w["t"] >= before}
        assert off == set(range(1, 7))


def test_a_follower_with_a_rate_moves_to_its_goal_over_time(tmp_path):
    from lerobot.motors import Motor, MotorNormMode
    from lerobot.motors.feetech import FeetechMotorsBus

    rate = 2000.0  # raw steps per second
    with FeetechEmulator.start(tmp_path, role="follower", rate=rate, positions={i: 2048 for i in range(1, 7)}) as arm:
        arm.write(2, "Torque_Enable", 1)
        bus = FeetechMotorsBus(arm.port, {"lift": Motor(2, "sts3215", MotorNormMode.DEGREES)})
        bus.connect()
        try:
            bus.write("Goal_Position", "lift", 3048, normalize=False, num_retry=2)
            written = arm.goal_log()[-1]["t"]  # when the servo took the goal (answered WRITE: already logged)
            while True:
                before = time.monotonic()
                present = bus.read("Present_Position", "lift", normalize=False, num_retry=2)
                after = time.monotonic()
                low, high = (min(3048, 2048 + rate * (t - written)) for t in (before, after))
                assert int(low) - 1 <= present <= high + 1, (before - written, present, after - written)
                if present == 3048:
                    break
                time.sleep(0.05)
            assert after - written >= 0.49, "1000 steps at 2000 steps/s take 0.5 s"
        finally:
            bus.disconnect(disable_torque=False)


# -- Koch leader on Dynamixel ---------------------------------------------------------------------------------


def test_koch_leader_reads_its_positions_over_dynamixel_protocol_2(tmp_path):
    from lerobot.teleoperators.koch_leader import KochLeader, KochLeaderConfig

    with DynamixelEmulator.start(tmp_path) as arm:
        arm.write_calibration_file(tmp_path / "cal", "koch")
        leader = KochLeader(KochLeaderConfig(port=arm.port, id="koch", calibration_dir=tmp_path / "cal"))
        connect_device(leader)
        try:
            assert leader.is_calibrated
            # configure() holds the gripper at gripper_open_pos (50 %) with torque on
            grip = [g for g in arm.goal_log() if g["motor"] == "gripper"]
            assert grip and arm.action_of({6: grip[-1]["value"]})["gripper.pos"] == pytest.approx(50.0, abs=arm.tolerance("gripper"))
            arm.set_action({"shoulder_lift.pos": 40.0, "elbow_flex.pos": -25.0, "gripper.pos": 80.0})
            action = read_retrying(leader.get_action)
            for motor, value in (("shoulder_lift", 40.0), ("elbow_flex", -25.0), ("gripper", 80.0)):
                assert action[f"{motor}.pos"] == pytest.approx(value, abs=arm.tolerance(motor))
            # FF FF FD inside a value is byte-stuffed both ways
            leader.bus.write("Homing_Offset", "shoulder_pan", -131073, normalize=False, num_retry=2)  # bytes FF FF FD FF
            assert arm.read(1, "Homing_Offset") == -131073
            assert leader.bus.read("Homing_Offset", "shoulder_pan", normalize=False, num_retry=2) == -131073
            # EEPROM writes with torque on are refused, as on a real XL330
            with pytest.raises(RuntimeError, match="Writing or Reading is not available"):
                leader.bus.write("Homing_Offset", "gripper", 0, normalize=False, num_retry=2)
            arm.unplug()
            with pytest.raises(ConnectionError, match="There is no status packet"):
                leader.get_action()
            arm.replug()
            assert read_retrying(leader.get_action)["shoulder_lift.pos"] == pytest.approx(40.0, abs=arm.tolerance("shoulder_lift"))
        finally:
            leader.disconnect()
        assert {w["id"] for w in arm.torque_log() if w["value"] == 0} == set(range(1, 7))


# -- the emulator's own life ----------------------------------------------------------------------------------


def test_the_emulator_process_ends_when_its_test_process_dies(tmp_path):
    script = ("import sys, time; from pathlib import Path; from tests.servo_emulator import FeetechEmulator; "
              f"arm = FeetechEmulator.start(Path({str(tmp_path)!r})); print(arm.proc.pid, flush=True); time.sleep(60)")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT, env=env)
    try:
        child = int(parent.stdout.readline())
        assert os.path.exists(f"/proc/{child}")
        os.kill(parent.pid, signal.SIGKILL)
        parent.wait()
        wait_until(lambda: not os.path.exists(f"/proc/{child}") or " Z " in open(f"/proc/{child}/stat").read(), 10,
                   "the emulator to exit after its parent died")
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def test_a_recorded_motion_file_loops_and_a_step_by_hand_overrides_it(tmp_path):
    import numpy as np

    motion = tmp_path / "wave.npz"  # shoulder_pan and wrist_flex (ids 1 and 4): 1000 -> 3000 in 1 s, then again
    np.savez(motion, t=np.array([0.0, 1.0]), positions=np.array([[1000, 1500], [3000, 2500]]), ids=np.array([1, 4]))
    with FeetechEmulator.start(tmp_path) as arm:
        started = arm.play(motion)
        checked = 0
        while checked < 3 or time.monotonic() - started < 1.3:  # past the loop's restart at 1 s
            before = time.monotonic()
            pan = arm.positions()[1]
            after = time.monotonic()
            low, high = (1000 + 2000 * ((t - started) % 1.0) for t in (before, after))
            if low <= high:  # not across the loop's wrap-around
                assert low - 1 <= pan <= high + 1, (pan, low, high)
                checked += 1
            time.sleep(0.3)
        arm.set_positions({1: 2222})
        first = arm.positions()
        time.sleep(0.1)
        second = arm.positions()
        assert first[1] == second[1] == 2222  # held by hand: the motion no longer drives it
        assert first[4] != second[4]  # wrist_flex still plays (500 steps/s)


def test_bad_commands_are_answered_without_ending_the_emulator(tmp_path):
    from tests.servo_emulator import EmulatorError

    with FeetechEmulator.start(tmp_path) as arm:
        with pytest.raises(EmulatorError, match="no servo with id 9"):
            arm.set_positions({9: 100})
        with pytest.raises(EmulatorError, match="unknown command"):
            arm.command("dance")
        assert arm.alive() and arm.positions()[1] == round(SO101_CALIBRATION["shoulder_pan"].mid)
    assert not arm.alive()
    assert json.loads(json.dumps(arm.writes())) == arm.writes()
