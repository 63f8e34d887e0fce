"""The SpaceMouse reading thread, fed real report bytes by a stand-in HID handle, ending in Commands.

The stand-in replaces only the USB hardware (this kernel has no uhid to make a
virtual device): it hands out report bytes through the same read()/close()
calls hidapi's handle has, and raises hidapi's OSError on unplug.
"""

from __future__ import annotations

import queue
import shutil
import subprocess
import time

import numpy as np
import pytest

from devices.base import DeviceError
from devices.registry import DeviceOptions, make_device, spacemouse_options
from devices.spacemouse import SpaceMouseDevice, find_spacemice, open_hid, open_problem, spacenavd_running
from devices.spacemouse_protocol import encode_buttons, encode_combined, encode_separate

DT = 1 / 30
POS, ROT = 0.2, 1.0
UNPLUG = object()


class StandInHandle:
    """Hands out queued report bytes like hidapi's device.read(max_length, timeout_ms)."""

    def __init__(self) -> None:
        self.queue: queue.Queue = queue.Queue()
        self.closed = False

    def feed(self, *reports: bytes) -> None:
        for r in reports:
            self.queue.put(r)

    def unplug(self) -> None:
        self.queue.put(UNPLUG)

    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]:
        try:
            item = self.queue.get(timeout=timeout_ms / 1000)
        except queue.Empty:
            return []
        if item is UNPLUG:
            raise OSError("read error")
        return list(item)[:max_length]

    def close(self) -> None:
        self.closed = True


class Port:
    """Where the device is plugged: the opener fails while unplugged, else returns a fresh handle."""

    def __init__(self) -> None:
        self.plugged = True
        self.handles: list[StandInHandle] = []
        self.attempts = 0

    def open(self) -> StandInHandle:
        self.attempts += 1
        if not self.plugged:
            raise DeviceError("SpaceMouse Compact is not connected")
        self.handles.append(StandInHandle())
        return self.handles[-1]


def wait_for(predicate, timeout=30.0):  # generous: a loaded machine stalls threads, and a pass returns at once
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.005)
    return predicate()


def settle(device: SpaceMouseDevice, count: int) -> None:
    assert wait_for(lambda: device.reports >= count), f"only {device.reports} of {count} reports parsed"


@pytest.fixture
def port():
    return Port()


@pytest.fixture
def mouse(port):
    devices = []

    def make(**kw) -> SpaceMouseDevice:
        kw.setdefault("reconnect_interval", 0.05)
        d = SpaceMouseDevice(port.open, pos_speed=POS, rot_speed=ROT, deadzone=0.0, **kw)
        d.start()
        devices.append(d)
        return d

    yield make
    for d in devices:
        d.close()


def test_separate_reports_become_a_held_world_motion(port, mouse):
    d = mouse(stance="behind")
    # push the cap fully away and twist it left (yaw), as a SpaceNavigator reports it
    t_report, r_report = encode_separate(0, -350, 0, 0, 0, -350)
    port.handles[0].feed(t_report, r_report)
    settle(d, 2)
    for _ in range(3):  # no new reports: the last deflection holds
        (cmd,) = d.poll(None, DT)
        assert np.allclose(cmd.translation, [POS * DT, 0, 0])
        assert np.allclose(cmd.rotation, [0, 0, ROT * DT])
        assert cmd.frame == "world" and cmd.arm == 0 and cmd.source == "spacemouse"
        time.sleep(0.02)
    # release: the device sends zero reports, then nothing
    port.handles[0].feed(*encode_separate(0, 0, 0, 0, 0, 0))
    settle(d, 4)
    assert d.poll(None, DT) == []


def test_combined_report_and_facing_stance_and_sensitivity(port, mouse):
    d = mouse(stance="facing", sensitivity=0.5)
    port.handles[0].feed(encode_combined(175, 0, -350, 0, 0, 0))  # half right, fully lifted
    settle(d, 1)
    (cmd,) = d.poll(None, DT)
    assert np.allclose(cmd.translation, 0.5 * POS * DT * np.array([0, 0.5, 1.0]))
    assert np.allclose(cmd.rotation, 0)


def test_toggle_button_press_inside_one_tick_gives_one_toggle(port, mouse):
    d = mouse()
    port.handles[0].feed(encode_buttons(1), encode_buttons(0))
    settle(d, 2)
    cmds = d.poll(None, DT)
    assert [c.gripper for c in cmds] == ["toggle"]
    assert d.poll(None, DT) == []


def test_hold_mode_closes_while_held_and_right_button_event(port, mouse):
    d = mouse(gripper_mode="hold", right_button="save", arm=1)
    port.handles[0].feed(encode_buttons(1))
    settle(d, 1)
    assert [(c.gripper, c.arm) for c in d.poll(None, DT)] == [("close", 1)]
    port.handles[0].feed(encode_buttons(0b11), encode_buttons(0))
    settle(d, 3)
    cmds = d.poll(None, DT)
    assert [c.events for c in cmds if c.events] == [("save",)]
    assert [c.gripper for c in cmds if c.gripper] == ["open"]


def test_right_button_frame_switches_deltas_to_the_end_effector_frame(port, mouse):
    d = mouse(right_button="frame")
    port.handles[0].feed(encode_buttons(2), encode_buttons(0), encode_combined(350, 0, 0, 0, 0, 0))
    settle(d, 3)
    (cmd,) = d.poll(None, DT)
    assert cmd.frame == "ee" and not cmd.events


def test_unplug_mid_stream_is_survived_and_the_device_reconnects(port, mouse):
    d = mouse()
    port.handles[0].feed(encode_combined(0, -350, 0, 0, 0, 0))
    settle(d, 1)
    assert d.poll(None, DT) and d.status() == "connected"
    port.plugged = False
    port.handles[0].unplug()
    assert wait_for(lambda: d.status() == "disconnected")
    assert port.handles[0].closed
    assert d.poll(None, DT) == []  # the last deflection must not keep driving the arm
    tries = port.attempts
    assert wait_for(lambda: port.attempts >= tries + 3), "it should keep trying to reopen"
    assert "not connected" in d.problem
    port.plugged = True
    assert wait_for(lambda: d.status() == "connected")
    port.handles[-1].feed(encode_combined(350, 0, 0, 0, 0, 0))
    settle(d, 2)
    (cmd,) = d.poll(None, DT)
    assert np.allclose(cmd.translation, [0, -POS * DT, 0])


def test_two_spacemice_drive_two_arms(mouse):
    left_port, right_port = Port(), Port()
    devices = [SpaceMouseDevice(p.open, name=f"spacemouse:{i}", arm=i, deadzone=0.0) for i, p in enumerate((left_port, right_port))]
    try:
        for d in devices:
            d.start()
        left_port.handles[0].feed(encode_combined(0, 0, -350, 0, 0, 0))
        right_port.handles[0].feed(encode_combined(0, 0, 350, 0, 0, 0))
        for d in devices:
            settle(d, 1)
        cmds = [c for d in devices for c in d.poll(None, DT)]
        assert [(c.arm, np.sign(c.translation[2])) for c in cmds] == [(0, 1.0), (1, -1.0)]
    finally:
        for d in devices:
            d.close()


def test_bad_options_are_one_line_errors():
    with pytest.raises(DeviceError, match="stance"):
        SpaceMouseDevice(Port().open, stance="sideways")
    with pytest.raises(DeviceError, match="right-button"):
        SpaceMouseDevice(Port().open, right_button="explode")
    with pytest.raises(DeviceError, match="bad SpaceMouse option"):
        spacemouse_options("1:wobble", DeviceOptions())
    index, kw = spacemouse_options("1:facing:hold:right=save:sensitivity=0.5", DeviceOptions(pos_speed=0.3))
    assert index == 1
    assert kw["stance"] == "facing" and kw["gripper_mode"] == "hold" and kw["right_button"] == "save"
    assert kw["sensitivity"] == 0.5 and kw["pos_speed"] == 0.3


def test_no_spacemouse_here_is_a_clear_error():
    """Without a SpaceMouse plugged in the error says so (with one, the device is built)."""
    if find_spacemice():
        assert make_device("spacemouse", DeviceOptions()) is not None
        return
    with pytest.raises(DeviceError, match="no SpaceMouse found"):
        make_device("spacemouse", DeviceOptions())


def test_unplugged_path_and_spacenavd_holding_it_say_what_to_do(tmp_path):
    info = {"path": b"/dev/hidraw-gone", "model": "SpaceMouse Compact"}
    assert "unplugged" in open_problem(info)
    with pytest.raises(DeviceError, match="unplugged"):
        open_hid(info)
    # a process named spacenavd runs, and the node cannot be opened as a HID device
    daemon_exe = tmp_path / "spacenavd"
    shutil.copy(shutil.which("sleep"), daemon_exe)
    daemon = subprocess.Popen([str(daemon_exe), "30"])
    try:
        assert wait_for(spacenavd_running)
        with pytest.raises(DeviceError, match=r"spacenavd is holding it.*systemctl stop spacenavd"):
            open_hid({"path": b"/dev/null", "model": "SpaceMouse Compact"})
    finally:
        daemon.kill()
        daemon.wait()
    with pytest.raises(DeviceError, match="cannot open /dev/null") as err:
        open_hid({"path": b"/dev/null", "model": "SpaceMouse Compact"})
    assert "spacenavd" not in str(err.value)
