"""`teleop devices` and `teleop run --device keyboard,...` as a user runs them, with and without a display."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time

import numpy as np
import pytest

from devices.base import DeviceError
from devices.registry import DeviceOptions, open_devices
from tests.support import ROOT, assert_one_line_error, run_teleop, write_script, xdotool

POS = 0.2


def teleop(*args: str, display: str | None, timeout: float = 120) -> subprocess.CompletedProcess:
    """`teleop ARGS` in a fresh process with DISPLAY set to `display` (None: no display at all); forked from the
    warm process when it may be (DISPLAY is read when used; pynput and the X libraries are not among its imports)."""
    return run_teleop(list(args), env_for(display), ROOT, timeout)


def env_for(display: str | None) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "XDG_SESSION_TYPE")}
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    if display:
        env["DISPLAY"] = display
    return env


def rows_by_name(result: subprocess.CompletedProcess) -> dict[str, dict]:
    assert result.returncode == 0, result.stderr
    rows = json.loads(result.stdout)["devices"]
    assert isinstance(rows, list)
    for row in rows:
        assert {"name", "kind", "available", "reason"} <= set(row), row
        assert isinstance(row["available"], bool) and row["reason"]
    return {row["name"]: row for row in rows}


def test_devices_json_without_display_says_why_the_keyboard_is_unavailable():
    rows = rows_by_name(teleop("devices", "--json", display=None))
    assert rows["keyboard"]["available"] is False
    assert "DISPLAY is not set" in rows["keyboard"]["reason"]
    assert rows["gizmo"]["available"] and rows["script"]["available"]
    mice = [r for r in rows.values() if r["kind"] == "spacemouse"]
    assert mice, "a SpaceMouse row (found, or why none) must always be listed"
    if not any(m["available"] for m in mice):
        assert all(m["reason"] for m in mice)


def test_devices_with_a_display_lists_the_keyboard_and_prints_bindings_and_setup(xvfb):  # noqa: F811
    rows = rows_by_name(teleop("devices", "--json", display=xvfb))
    assert rows["keyboard"]["available"] is True
    text = teleop("devices", display=xvfb)
    assert text.returncode == 0
    assert "keyboard    keyboard    yes" in text.stdout
    assert "toggle the gripper" in text.stdout and "backspace" in text.stdout
    assert 'ATTRS{idVendor}=="256f"' in text.stdout and "systemctl stop spacenavd" in text.stdout


def test_run_without_display_goes_on_with_the_script_and_says_so_in_one_line(tmp_path):
    script = write_script(tmp_path / "s.json", [{"duration": 0.3, "move": [0, 0, 0.02]}])
    result = teleop("run", "--device", f"keyboard,script:{script}", "--json", display=None)
    assert result.returncode == 0, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "keyboard" in lines[0] and "DISPLAY" in lines[0], lines
    assert json.loads(result.stdout)["devices"] == ["script:s.json"]


def test_run_with_only_a_keyboard_and_no_display_is_a_one_line_error():
    result = teleop("run", "--device", "keyboard", "--seconds", "0.1", display=None)
    assert_one_line_error(result, "keyboard", "no display")


def test_open_devices_carries_on_past_failures_and_fails_only_when_none_start(tmp_path, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    script = write_script(tmp_path / "s.json", [{"duration": 0.1}])
    started, problems = open_devices(f"keyboard, nonsense ,script:{script}", DeviceOptions())
    assert [d.kind for d in started] == ["script"]
    assert [p.split(":")[0] for p in problems] == ["keyboard", "nonsense"]
    with pytest.raises(DeviceError, match="no device could start: keyboard: no display"):
        open_devices("keyboard", DeviceOptions())


def test_holding_w_in_teleop_run_moves_the_end_effector_forward_by_speed_times_time(xvfb, tmp_path):  # noqa: F811
    """End to end: pynput in `teleop run`, a key held by xdotool, the recorded EE target and pose."""
    script = write_script(tmp_path / "s.json", [{"duration": 0.2, "gripper": "open"}])
    record = tmp_path / "rec"
    cmd = [sys.executable, "-m", "teleop", "run", "--device", f"keyboard,script:{script}", "--seconds", "4",
           "--pos-speed", str(POS), "--record", str(record), "--json"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env_for(xvfb), cwd=ROOT)
    try:
        deadline = time.monotonic() + 90
        while not (record.exists() and any(record.iterdir())):  # the episode file opens as the loop starts
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "teleop run did not start its episode"
            time.sleep(0.02)
        time.sleep(0.5)  # the script's short step is over: only the keyboard drives now
        down = xdotool(xvfb, "keydown", "w")
        time.sleep(1.0)
        up = xdotool(xvfb, "keyup", "w")
        assert proc.poll() is None, "the run ended before the key was released"
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    summary = json.loads(out)
    assert summary["devices"] == ["keyboard", "script:s.json"]
    from replay.episode import load_episode

    episode = load_episode(summary["files"][0])
    moved = episode.ee_target[-1, 0, :3] - episode.ee_target[0, 0, :3]
    # Forward at the speed asked, tick by tick, for most of the time held: the distance over the wall-clock hold
    # is not asked for, since a loaded machine delivers X's key events late (the hold the run sees is shorter)
    dt = episode.meta.control_dt
    steps = np.diff(episode.ee_target[:, 0, 0])
    assert steps.max() == pytest.approx(POS * dt, rel=1e-3)
    assert (steps > 0.5 * POS * dt).sum() >= 0.5 * (up - down) / dt
    assert abs(moved[1]) < 1e-3 and abs(moved[2]) < 1e-3
    reached = episode.ee_pose[-1, 0, :3] - episode.ee_pose[0, 0, :3]
    assert reached[0] == pytest.approx(moved[0], rel=0.1)
    sources = {c.get("source") for step in episode.commands for c in step}
    assert "keyboard" in sources
    assert np.all(np.diff(episode.ee_target[:, 0, 0]) >= -1e-9)  # never moved backward


# -- serial ports: leader and follower arms found through LeRobot's own buses --------------------------------


@pytest.mark.e2e
def test_devices_probes_named_ports_and_lists_the_servos_and_arm_types_they_fit(tmp_path):
    """A Feetech bus (6 x STS3215, 1 Mbaud) and a Dynamixel one (6 x XL330-M077 at 57,600 baud: found by the
    third probe, after Feetech and Dynamixel at 1 Mbaud found nothing) on ptys named with --port."""
    import lerobot.motors.feetech  # noqa: F401 - the hardware extra: its absence fails the test, never skips it
    from tests.servo_emulator import DynamixelEmulator, FeetechEmulator

    with FeetechEmulator.start(tmp_path) as so101, DynamixelEmulator.start(tmp_path, baudrate=57_600) as koch:
        ports = ("--port", so101.port, "--port", koch.port)
        result = teleop("devices", "--json", *ports, display=None)
        assert result.returncode == 0, result.stderr
        serial = {row["port"]: row for row in json.loads(result.stdout)["serial"]}
        assert {"port", "by_id", "servos", "fits"} <= set(serial[so101.port])
        assert serial[so101.port]["servos"] == [
            {"id": i, "model": "sts3215", "model_number": 777, "protocol": "feetech", "baudrate": 1_000_000} for i in range(1, 7)]
        assert set(serial[so101.port]["fits"]) == {"so100_leader", "so100_follower", "so101_leader", "so101_follower"}
        assert [(s["id"], s["model"], s["baudrate"]) for s in serial[koch.port]["servos"]] == [(i, "xl330-m077", 57_600) for i in range(1, 7)]
        assert serial[koch.port]["fits"] == ["koch_leader"]
        assert serial[so101.port]["by_id"] is None  # a pty has no /dev/serial/by-id link
        # the probe only pings and reads: nothing was written to the servos
        assert so101.writes() == [] and koch.writes() == []
        assert set(so101.stats()["packets"]) == {"ping", "read"}

        text = teleop("devices", *ports, display=None)
        assert text.returncode == 0, text.stderr
        lines = {line.split()[0]: line for line in text.stdout.splitlines() if line.startswith("/dev/")}
        assert "6 STS3215 at ids 1-6" in lines[so101.port] and "so101_leader" in lines[so101.port]
        assert "6 XL330-M077 at ids 1-6" in lines[koch.port] and "57600 baud" in lines[koch.port] and "koch_leader" in lines[koch.port]


@pytest.mark.e2e
def test_devices_reports_a_port_another_process_holds_and_does_not_ping_it(tmp_path):
    import lerobot.motors.feetech  # noqa: F401 - the hardware extra: its absence fails the test, never skips it
    from tests.servo_emulator import FeetechEmulator

    with FeetechEmulator.start(tmp_path) as arm:
        fd = os.open(arm.port, os.O_RDWR | os.O_NOCTTY)  # as a running LeRobot session would
        try:
            result = teleop("devices", "--json", "--port", arm.port, display=None)
        finally:
            os.close(fd)
        assert result.returncode == 0, result.stderr
        row = next(r for r in json.loads(result.stdout)["serial"] if r["port"] == arm.port)
        assert row["servos"] == [] and row["problem"].startswith("busy: in use by") and str(os.getpid()) in row["problem"]
        assert arm.stats()["packets"] == {}


@pytest.mark.e2e
def test_devices_without_lerobot_lists_ports_and_says_in_one_line_what_probing_needs(tmp_path):
    """LeRobot made unimportable in the child (as if the hardware extra were not installed)."""
    from tests.servo_emulator import FeetechEmulator

    with FeetechEmulator.start(tmp_path) as arm:
        code = ("import sys; sys.modules['lerobot'] = None; from teleop.cli.entry import main; "
                f"sys.exit(main(['devices', '--port', {arm.port!r}] + sys.argv[1:]))")
        for extra in ([], ["--json"]):
            result = subprocess.run([sys.executable, "-c", code, *extra], capture_output=True, text=True, timeout=120,
                                    env=env_for(None), cwd=ROOT)
            assert result.returncode == 0, result.stderr
            if extra:
                out = json.loads(result.stdout)
                assert "pip install 'mujoco-teleop[hardware]'" in out["serial_note"]
                row = next(r for r in out["serial"] if r["port"] == arm.port)
                assert row["servos"] == [] and "not installed" in row["problem"]
            else:
                hints = [line for line in result.stdout.splitlines() if "mujoco-teleop[hardware]" in line]
                assert len(hints) == 1, result.stdout
                assert any(line.startswith(arm.port) for line in result.stdout.splitlines())
        assert arm.stats()["packets"] == {}


@pytest.mark.e2e
def test_devices_with_a_port_that_does_not_exist_is_a_one_line_error(tmp_path):
    result = teleop("devices", "--port", str(tmp_path / "ttyUSB9"), display=None)
    assert_one_line_error(result, "--port", "no such device")


def test_serial_port_lines_and_arm_types_from_what_answered():
    from devices.serial_ports import FoundServo, SerialPort, fits

    koch_follower = [FoundServo(i, "xl430-w250" if i < 3 else "xl330-m288", 0, "dynamixel", 1_000_000) for i in range(1, 7)]
    assert fits(koch_follower) == ["koch_follower"]
    assert fits(koch_follower[:5]) == []  # the gripper missing: not a whole arm
    assert fits([FoundServo(i, "sts3215", 777, "dynamixel", 57_600) for i in range(1, 7)]) == []  # wrong protocol
    port = SerialPort("/dev/ttyACM0", probed=True, servos=koch_follower[:2] + koch_follower[3:])
    assert port.summary().startswith("2 XL430-W250, 3 XL330-M288 at ids 1-2, 4-6 (dynamixel, 1000000 baud)")
    assert SerialPort("/dev/ttyACM1", probed=True).summary().startswith("no servo answered")
