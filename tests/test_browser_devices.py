"""Devices fed by the operator's browser: a gamepad (Gamepad API states) and a SpaceMouse over WebHID
(real report bytes, as WebHID hands them: report id apart from the data), read as the session reads them."""

from __future__ import annotations

import time

import numpy as np
import pytest

import teleop
from devices.gamepad import A, B, BACK, LB, LT, N_BUTTONS, RB, RT, START, STALE_S, GamepadDevice, stick
from devices.spacemouse_protocol import encode_buttons, encode_combined, encode_separate
from devices.webhid import BrowserHidHandle, WebHidSpaceMouse
from tests.support import wait_until

DT = 1.0 / 30


def pad(device: GamepadDevice, axes=(0, 0, 0, 0), pressed: dict[int, float] | None = None) -> None:
    buttons = np.zeros(N_BUTTONS)
    for index, value in (pressed or {}).items():
        buttons[index] = value
    device.push(list(axes), list(buttons), "Xbox Wireless Controller (STANDARD GAMEPAD)")


def test_stick_deadzone_is_radial_and_reaches_full_scale():
    assert stick(0.1, 0.05) == (0.0, 0.0)
    x, y = stick(1.0, 0.0)
    assert (x, y) == pytest.approx((1.0, 0.0))
    x, y = stick(0.0, -0.5)
    assert x == 0.0 and -0.5 < y < 0.0
    x, y = stick(0.8, 0.8)  # beyond the unit circle: capped at full deflection
    assert np.hypot(x, y) == pytest.approx(1.0)


def test_gamepad_sticks_and_triggers_move_the_target_in_the_world_frame():
    g = GamepadDevice(pos_speed=0.3, rot_speed=1.0)
    pad(g, axes=(0, -1, 0, 0))  # left stick pushed up
    (cmd,) = g.poll(None, DT)
    np.testing.assert_allclose(cmd.translation, [0.3 * DT, 0, 0])  # away from the base
    pad(g, axes=(1, 0, 0, 0))  # left stick right
    np.testing.assert_allclose(g.poll(None, DT)[0].translation, [0, -0.3 * DT, 0])  # robot's right
    pad(g, pressed={RT: 1.0})
    np.testing.assert_allclose(g.poll(None, DT)[0].translation, [0, 0, 0.3 * DT])
    pad(g, pressed={LT: 1.0})
    np.testing.assert_allclose(g.poll(None, DT)[0].translation, [0, 0, -0.3 * DT])
    pad(g, axes=(0, 0, 0, -1))  # right stick up, no shoulder: up as well
    np.testing.assert_allclose(g.poll(None, DT)[0].translation, [0, 0, 0.3 * DT])
    pad(g, axes=(0, 0, 1, 0))  # right stick right: yaw right
    np.testing.assert_allclose(g.poll(None, DT)[0].rotation, [0, 0, -DT])
    pad(g, axes=(0, 0, 1, -1), pressed={LB: 1.0})  # LB: roll and pitch
    cmd = g.poll(None, DT)[0]
    assert cmd.rotation[0] > 0 and cmd.rotation[1] > 0 and cmd.rotation[2] == 0 and not cmd.translation.any()
    pad(g, axes=(0, 0, 1, 0), pressed={RB: 1.0})  # RB: yaw
    cmd = g.poll(None, DT)[0]
    assert cmd.rotation[2] < 0 and cmd.rotation[0] == 0
    pad(g, axes=(0.05, -0.08, 0.1, 0.0), pressed={LT: 0.03})  # resting: drift inside the deadzones
    assert g.poll(None, DT) == []


def test_gamepad_buttons_are_edges_even_between_ticks():
    g = GamepadDevice()
    pad(g, pressed={A: 1.0})
    pad(g)  # released before the loop polled: still one toggle
    pad(g, pressed={A: 1.0})
    pad(g, pressed={A: 1.0})  # held: no second edge
    commands = g.poll(None, DT)
    assert [c.gripper for c in commands] == ["toggle", "toggle"]
    for button, event in ((B, "reset"), (START, "record"), (BACK, "discard")):
        pad(g, pressed={button: 1.0})
        pad(g)
        assert [c.events for c in g.poll(None, DT)] == [(event,)]


def test_gamepad_values_are_clipped_and_a_silent_pad_releases(monkeypatch):
    g = GamepadDevice(pos_speed=0.1)
    g.push([5.0, float("nan"), -9.0, 0.0, 3.0], [2.0] * 40, "x" * 500)
    assert len(g.pad_id) == 120
    cmd = [c for c in g.poll(None, DT) if c.translation.any()][0]
    assert np.all(np.abs(cmd.translation) <= 0.1 * DT * 2 + 1e-12)
    pad(g, axes=(0, -1, 0, 0))
    assert g.poll(None, DT)
    later = time.monotonic() + STALE_S + 0.1
    monkeypatch.setattr(time, "monotonic", lambda: later)
    assert g.poll(None, DT) == []  # the browser stopped sending: nothing moves
    assert "no pad" in g.status()


def test_record_event_starts_then_saves(tmp_path):
    session = teleop.Session("lift", "panda", seed=0)
    g = GamepadDevice()
    with teleop.Recorder(session, tmp_path, verify="off") as rec:
        pad(g, pressed={START: 1.0})
        session.step(g.poll(session.controller, session.dt))
        assert rec.recording
        pad(g)
        for _ in range(5):
            session.step(g.poll(session.controller, session.dt))
        pad(g, pressed={START: 1.0})
        session.step(g.poll(session.controller, session.dt))
        assert not rec.recording and rec.episodes_saved == 1


@pytest.mark.parametrize("layout", ["separate", "combined"])
def test_webhid_reports_go_through_the_spacemouse_parser(layout):
    device = WebHidSpaceMouse(pos_speed=0.2, rot_speed=1.0, deadzone=0.0)
    device.start()
    try:
        assert "waiting" in device.status() and device.poll(None, DT) == []
        handle = device.source.connect("SpaceMouse Compact")
        # WebHID gives (reportId, data): split the real report bytes the same way
        reports = list(encode_separate(350, 0, 0, 0, 0, 0)) if layout == "separate" else [encode_combined(350, 0, 0, 0, 0, 0)]
        for report in reports:
            assert handle.push(report[0], report[1:])
        assert wait_until(lambda: device.reports == len(reports), 30.0)
        assert device.status() == "SpaceMouse Compact in a browser"
        (cmd,) = device.poll(None, DT)
        assert np.linalg.norm(cmd.translation) == pytest.approx(0.2 * DT, rel=0.02)  # full deflection, one axis
        button = encode_buttons(1)
        handle.push(button[0], button[1:])  # left button: the gripper
        assert wait_until(lambda: device.reports == len(reports) + 1, 30.0)
        assert [c.gripper for c in device.poll(None, DT)] == ["toggle"]
        assert not handle.push(1, bytes(70))  # too long for a SpaceMouse report: dropped
        device.source.disconnect(handle)  # the browser went away: motion stops at once
        assert wait_until(lambda: not device._connected, 30.0)
        assert device.poll(None, DT) == []
        assert "waiting" in device.status()
    finally:
        device.close()


def test_webhid_reader_waits_for_a_browser_without_polling_and_wakes_when_one_connects():
    device = WebHidSpaceMouse(deadzone=0.0)
    tries = []
    opener = device._opener
    device._opener = lambda: (tries.append(time.monotonic()), opener())[1]
    device.start()
    try:
        time.sleep(0.6)
        assert len(tries) <= 2, f"the reader polled for a browser's device {len(tries)} times in 0.6 s"
        started = time.monotonic()
        handle = device.source.connect("SpaceMouse Compact")
        report = encode_combined(350, 0, 0, 0, 0, 0)
        handle.push(report[0], report[1:])
        assert wait_until(lambda: device.reports == 1, 30.0)
        assert time.monotonic() - started < 0.5, "connecting a device did not wake the reader"
    finally:
        closing = time.monotonic()
        device.close()
    assert time.monotonic() - closing < 1.0 and not device._thread.is_alive()


def test_browser_hid_handle_reads_like_hidraw():
    handle = BrowserHidHandle()
    assert handle.read(64, 10) == []
    handle.push(3, b"\x01\x00")
    assert handle.read(64, 0) == [3, 1, 0]
    handle.close()
    with pytest.raises(OSError):
        handle.read(64, 10)
    assert not handle.push(1, b"\x00" * 6)


def _about_z(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([np.cos(a / 2), 0.0, 0.0, np.sin(a / 2)])


def _about_x(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([np.cos(a / 2), np.sin(a / 2), 0.0, 0.0])


def _yaw_of(q: np.ndarray) -> float:
    w, x, y, z = q
    return np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))


def test_phone_moves_the_target_only_while_the_clutch_is_held():
    from devices.phone import PhoneDevice, quat_mul

    session = teleop.Session("lift", "panda", seed=0)
    phone = PhoneDevice()
    start_pos, start_quat = (np.array(v) for v in session.controller.target_pose())
    facing_north = _about_z(90)  # the operator faces north: that is the robot's +x at the press
    phone.push_pose(facing_north, clutch=False)
    phone.push_pose(quat_mul(_about_z(30), facing_north), clutch=False)  # turned without the clutch
    session.step(phone.poll(session.controller, session.dt))
    np.testing.assert_allclose(session.controller.target_pose()[1], start_quat, atol=1e-12)

    phone.push_pose(facing_north, clutch=True)
    session.step(phone.poll(session.controller, session.dt))  # the press: motion counts from here
    phone.push_pose(quat_mul(_about_z(30), facing_north), clutch=True)  # 30 degrees left
    session.step(phone.poll(session.controller, session.dt))
    turned = session.controller.target_pose()[1]
    assert _yaw_of(turned) - _yaw_of(start_quat) == pytest.approx(30.0, abs=0.5)
    np.testing.assert_allclose(session.controller.target_pose()[0], start_pos, atol=1e-9)  # no WebXR: rotation only

    phone.push_pose(quat_mul(_about_z(30), facing_north), clutch=False)  # let go...
    session.step(phone.poll(session.controller, session.dt))
    phone.push_pose(facing_north, clutch=False)  # ...and turn back freely
    session.step(phone.poll(session.controller, session.dt))
    np.testing.assert_allclose(session.controller.target_pose()[1], turned, atol=1e-12)


def test_phone_with_webxr_maps_forward_to_world_x_and_rejects_bad_poses():
    from devices.phone import PhoneDevice

    session = teleop.Session("lift", "panda", seed=0)
    phone = PhoneDevice(scale=0.5)
    start_pos = np.array(session.controller.target_pose()[0])
    facing_west = _about_z(180)  # phone's top edge toward earth -y... heading of +y rotated 180 deg: south
    assert phone.push_pose(facing_west, pos=[1.0, 2.0, 0.0], clutch=True)
    session.step(phone.poll(session.controller, session.dt))
    heading_dir = np.array([0.0, -1.0, 0.0])  # where the phone's top points: that is world +x now
    assert phone.push_pose(facing_west, pos=np.array([1.0, 2.0, 0.0]) + 0.1 * heading_dir + [0, 0, 0.04], clutch=True)
    session.step(phone.poll(session.controller, session.dt))
    np.testing.assert_allclose(session.controller.target_pose()[0], start_pos + [0.05, 0.0, 0.02], atol=1e-6)
    assert not phone.push_pose([0, 0, 0, 0], clutch=True)
    assert not phone.push_pose([1, 0, 0, 0], pos=[float("nan"), 0, 0])
    assert not phone.push_pose([1, 0, 0], clutch=True)
    phone.press("gripper")
    phone.press("record")
    commands = phone.poll(session.controller, session.dt)
    assert commands[0].gripper == "toggle" and commands[1].events == ("record",)


@pytest.mark.parametrize("message, why", [
    ({"type": "gamepad", "id": "x", "axes": [0, 2.0], "buttons": [], "connected": True}, "from -1 to 1"),
    ({"type": "gamepad", "id": "x", "axes": [0] * 9, "buttons": [], "connected": True}, "0 to 8"),
    ({"type": "gamepad", "id": "x", "axes": [True], "buttons": [], "connected": True}, "from -1 to 1"),
    ({"type": "gamepad", "id": "x", "axes": [], "buttons": [], "connected": "yes"}, "true or false"),
    ({"type": "gamepad", "id": "x", "axes": [], "buttons": [], "connected": True, "extra": 1}, "unknown field"),
    ({"type": "phone", "quat": [1, 1, 0, 0], "pos": None, "clutch": True}, "unit quaternion"),
    ({"type": "phone", "quat": [1, 0, 0, 0], "pos": [0, 0, 500], "clutch": True}, "from -100 to 100"),
    ({"type": "phone", "quat": [1, 0, 0], "pos": None, "clutch": True}, "4 numbers"),
    ({"type": "phone_button", "action": "explode"}, "must be one of"),
    ({"type": "hid", "report_id": 1, "data": [256]}, "0-255"),
    ({"type": "hid", "report_id": 300, "data": []}, "0 to 255"),
    ({"type": "hid", "report_id": 1, "data": [0] * 64}, "at most 63"),
    ({"type": "hid_connect", "product": "x" * 81}, "at most 80"),
])
def test_device_messages_out_of_range_are_rejected_with_a_reason(message, why):
    import json

    from teleop.web.shared.input_messages import Rejected, parse

    with pytest.raises(Rejected, match=why):
        parse(json.dumps(message))


def test_a_page_that_goes_away_lets_go_of_its_pad_phone_and_spacemouse():
    from devices.phone import PhoneDevice
    from teleop.web.shared.input_messages import Gamepad, Hid, HidConnect, Phone
    from teleop.web.session_page.page_devices import PageInputs

    pad, phone, mouse = GamepadDevice(), PhoneDevice(), WebHidSpaceMouse(deadzone=0.0)
    mouse.start()
    inputs = PageInputs(None, [pad, phone, mouse])
    try:
        inputs.opened(1, "127.0.0.1")
        inputs.received(1, Gamepad("pad", (0.0, -1.0), (), True))
        inputs.received(1, Phone((1.0, 0.0, 0.0, 0.0), None, True))
        inputs.received(1, HidConnect("SpaceMouse Compact"))
        report = encode_combined(0, -350, 0, 0, 0, 0)
        inputs.received(1, Hid(report[0], report[1:]))
        assert wait_until(lambda: mouse.reports == 1, 30.0)
        assert pad.poll(None, DT) and "held" in phone.status() and mouse.poll(None, DT)
        inputs.received(2, Gamepad("other", (), (), True))  # another page's pad now: page 1 no longer owns it
        inputs.closed(1)
        assert pad.poll(None, DT) == [] and "no phone" in phone.status()
        assert wait_until(lambda: not mouse._connected, 30.0) and mouse.poll(None, DT) == []
        inputs.received(3, Hid(1, b"\x00" * 12))  # reports before a hid_connect: not used
        assert inputs.unused == 1
    finally:
        mouse.close()
