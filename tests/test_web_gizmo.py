"""The gizmo device's mailbox, the registry branch, host/port checks and the served loop without a browser."""

from __future__ import annotations

import socket
import time

import numpy as np
import pytest

from devices.gizmo import SETTLE_S, GizmoDevice
from devices.registry import DeviceOptions, make_device
from teleop.errors import UsageError
from teleop.web.shared.net import check_port_free, exposure_warning, is_loopback, page_url


def test_gizmo_hands_over_only_the_newest_pose_once():
    g = GizmoDevice(n_arms=2)
    g.push(1, [0.1, 0.2, 0.3], [1, 0, 0, 0], "start")
    g.push(1, [0.4, 0.5, 0.6], [0, 1, 0, 0], "update")
    (command,) = g.poll(None, 0.01)
    assert command.arm == 1 and command.source == "gizmo"
    np.testing.assert_allclose(command.target_pos, [0.4, 0.5, 0.6])
    np.testing.assert_allclose(command.target_quat, [0, 1, 0, 0])
    assert g.poll(None, 0.01) == []
    assert g.last_input_time > 0 and g.drags == 1


def test_gizmo_ignores_bad_poses_and_arms():
    g = GizmoDevice(n_arms=1)
    g.push(3, [0, 0, 0], [1, 0, 0, 0])
    g.push(0, [np.nan, 0, 0], [1, 0, 0, 0])
    g.push(0, [0, 0], [1, 0, 0, 0])
    assert g.poll(None, 0.01) == []


def test_gizmo_is_busy_while_held_and_just_after():
    g = GizmoDevice(n_arms=1)
    assert not g.busy(0)
    g.push(0, [0, 0, 0.5], [1, 0, 0, 0], "start")
    g.poll(None, 0.01)
    assert g.busy(0)  # held
    g.push(0, [0, 0, 0.5], [1, 0, 0, 0], "end")
    g.poll(None, 0.01)
    assert g.busy(0)  # just let go
    time.sleep(SETTLE_S + 0.05)
    assert not g.busy(0)
    g.push(0, [0, 0, 0.5], [1, 0, 0, 0], "start")
    g.release()  # the browser went away mid-drag
    g.poll(None, 0.01)
    time.sleep(SETTLE_S + 0.05)
    assert not g.busy(0)


def test_registry_makes_a_gizmo_per_scene_arms():
    device = make_device("gizmo", DeviceOptions(n_arms=2))
    assert isinstance(device, GizmoDevice) and device.n_arms == 2 and device.kind == "gizmo"
    from devices.base import DeviceError

    with pytest.raises(DeviceError):
        make_device("gizmo:3", DeviceOptions())


def test_port_in_use_is_an_error_naming_the_port():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        with pytest.raises(UsageError, match=str(port)):
            check_port_free("127.0.0.1", port)


def test_host_checks():
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert exposure_warning("127.0.0.1", 8080) is None
    warning = exposure_warning("0.0.0.0", 8080)
    assert warning and "anyone who can reach" in warning and "8080" in warning
    with pytest.raises(UsageError):
        check_port_free("203.0.113.7", 8080)  # not an address of this machine
    assert page_url("127.0.0.1", 8080) == "http://127.0.0.1:8080"


def test_served_loop_runs_in_real_time_and_records(tmp_path):
    """The WebApp in-process, no browser: a loop paced to the wall clock, panel commands, save, exact replay check."""
    from teleop import Command, Recorder, Session
    from teleop.web.session_page.app import WebApp
    from teleop.web.session_page.serve_options import ServeOptions

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    session = Session()
    Recorder(session, tmp_path, ("mcap",), verify="background", on_error="stop")
    gizmo = GizmoDevice()
    app = WebApp(session, [gizmo], [], ServeOptions(port=port), camera=False)
    app.start()
    try:
        time.sleep(0.5)
        app.panel_device.push(Command(events=("start",)))
        pos, quat = session.controller.target_pose(0)
        for i in range(30):
            gizmo.push(0, pos + [0.003 * i, 0, -0.002 * i], quat)
            time.sleep(1 / 30)
        app.panel_device.push(Command(events=("save",)))
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not any(v is not None for v in app.verified.values()):
            time.sleep(0.1)
        status = app.status()
    finally:
        app.close()
    assert status["episodes_saved"] == 1
    assert list(status["verified"].values()) == [True]
    # paced to the wall clock, never faster (a loaded machine may run it slower: how fast it keeps up is
    # bench/web.py's serve_realtime_factor and web_update_ms, not a test's)
    assert 0 < status["realtime_factor"] < 1.15 and status["loop_hz"] > 0
    assert status["ee_pos"][0][0] > pos[0] + 0.05
    assert status["web_updates"] > 1 and status["web_update_ms"] > 0  # drawn as it moved, not only the first picture


def test_speed_sliders_set_keyboard_and_spacemouse_speeds():
    from teleop.control.session import Session
    from teleop.web.session_page.app import WebApp
    from teleop.web.session_page.serve_options import ServeOptions

    class HoldToMove:
        """Stands in for the keyboard: what the sliders change is its speeds."""

        name = kind = "keyboard"
        pos_speed, rot_speed = 0.15, 0.8

        def poll(self, view, dt):
            return []

        def status(self):
            return "connected"

        def close(self):
            pass

    device = HoldToMove()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    app = WebApp(Session(), [device, GizmoDevice()], ["spacemouse: no SpaceMouse found"], ServeOptions(port=port), camera=False)
    try:
        app.panel.pos_slider.value = 0.3
        app.panel.rot_slider.value = 1.5
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (device.pos_speed, device.rot_speed) != (0.3, 1.5):
            time.sleep(0.05)
        assert (device.pos_speed, device.rot_speed) == (0.3, 1.5)
        text = app.panel._devices_text()
        assert "keyboard" in text and "spacemouse" in text and "not started" in text
    finally:
        app.close()
