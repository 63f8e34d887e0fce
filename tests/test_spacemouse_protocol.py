"""SpaceMouse report parsing on the exact bytes devices send (report id, then int16 little-endian)."""

from __future__ import annotations

import numpy as np
import pytest

from devices.spacemouse_protocol import (
    FULL_SCALE,
    RawState,
    apply_report,
    encode_buttons,
    encode_combined,
    encode_separate,
    is_spacemouse,
    normalize,
    to_world,
)

# SpaceNavigator-style (separate layout): x=100, y=-50, z=350 then rx=-350, ry=0, rz=12
TRANSLATION_REPORT = bytes.fromhex("01 6400 ceff 5e01")
ROTATION_REPORT = bytes.fromhex("02 a2fe 0000 0c00")
# SpaceMouse Wireless-style (combined layout): the same six values in one 13-byte report
COMBINED_REPORT = bytes.fromhex("01 6400 ceff 5e01 a2fe 0000 0c00")


def test_separate_layout_reports_fill_each_half_and_hold_the_other():
    state = RawState()
    assert apply_report(state, TRANSLATION_REPORT) == "translation"
    assert state.axes == [100, -50, 350, 0, 0, 0]
    assert apply_report(state, list(ROTATION_REPORT)) == "rotation"  # hidapi returns a list of ints
    assert state.axes == [100, -50, 350, -350, 0, 12]
    # a later translation report leaves the rotation half as it was
    assert apply_report(state, bytes.fromhex("01 0000 0000 f6ff")) == "translation"
    assert state.axes == [0, 0, -10, -350, 0, 12]


def test_combined_layout_sets_all_six_axes():
    state = RawState()
    assert apply_report(state, COMBINED_REPORT) == "motion"
    assert state.axes == [100, -50, 350, -350, 0, 12]
    # the zero report a device sends after release
    assert apply_report(state, b"\x01" + bytes(12)) == "motion"
    assert state.axes == [0] * 6


def test_encoders_match_the_device_bytes():
    assert encode_separate(100, -50, 350, -350, 0, 12) == (TRANSLATION_REPORT, ROTATION_REPORT)
    assert encode_combined(100, -50, 350, -350, 0, 12) == COMBINED_REPORT
    assert encode_buttons(0b10) == bytes.fromhex("03 0200")


def test_buttons_and_ignored_reports():
    state = RawState(axes=[1, 2, 3, 4, 5, 6])
    assert apply_report(state, bytes.fromhex("03 0100")) == "buttons"
    assert state.buttons & 1 and not state.buttons & 2
    assert apply_report(state, bytes.fromhex("03 0300")) == "buttons"
    assert state.buttons == 3
    assert apply_report(state, bytes.fromhex("17 5a")) is None  # battery level on wireless models
    assert apply_report(state, b"\x01\x00") is None  # truncated
    assert apply_report(state, b"") is None
    assert state.axes == [1, 2, 3, 4, 5, 6]


def test_normalize_deadzone_is_continuous_and_full_scale_is_one():
    v = normalize([0, 5, -10, 350, -400, 175], deadzone=0.05)
    assert v[0] == 0 and v[1] == 0  # inside the deadzone (5/350 < 0.05)
    assert v[2] == 0  # 10/350 = 0.029 < 0.05
    assert v[3] == pytest.approx(1.0)
    assert v[4] == pytest.approx(-1.0)  # clipped beyond full scale
    assert v[5] == pytest.approx((0.5 - 0.05) / 0.95)
    just_outside = normalize([0.05 * FULL_SCALE + 0.35], deadzone=0.05)[0]
    assert 0 < just_outside < 0.002


def test_stances_map_pushes_to_the_documented_world_directions():
    push_away = normalize([0, -350, 0, 0, 0, 0], 0.0)  # HID y points toward the operator
    push_right = normalize([350, 0, 0, 0, 0, 0], 0.0)
    lift = normalize([0, 0, -350, 0, 0, 0], 0.0)  # HID z points down
    twist_ccw_from_above = normalize([0, 0, 0, 0, 0, -350], 0.0)  # right-handed about HID z (down)
    for stance, away, right in (("behind", [1, 0, 0], [0, -1, 0]), ("facing", [-1, 0, 0], [0, 1, 0])):
        assert np.allclose(to_world(push_away, stance)[0], away)
        assert np.allclose(to_world(push_right, stance)[0], right)
        assert np.allclose(to_world(lift, stance)[0], [0, 0, 1])
        trans, rot = to_world(twist_ccw_from_above, stance)
        assert np.allclose(trans, 0) and np.allclose(rot, [0, 0, 1])  # yaw left in the world


def test_device_filter():
    assert is_spacemouse(0x256F, 0xC635)  # SpaceMouse Compact
    assert is_spacemouse(0x256F, 0xC6FF)  # an unknown newer 3Dconnexion model
    assert not is_spacemouse(0x256F, 0xC650)  # CadMouse
    assert is_spacemouse(0x046D, 0xC626)  # SpaceNavigator
    assert not is_spacemouse(0x046D, 0xC52B)  # a Logitech receiver
    assert not is_spacemouse(0x1234, 0xC626)
    assert not is_spacemouse(0x256F, 0xC652, usage_page=0x01, usage=0x06)  # a receiver's keyboard interface
    assert is_spacemouse(0x256F, 0xC652, usage_page=0x01, usage=0x08)
