"""Keyboard device through real pynput on a private Xvfb display, keys sent by xdotool.

Needs the Debian packages xvfb and xdotool. Each module starts its own X
server (conftest.py's xvfb fixture) on a free display number (Xvfb -displayfd picks one) and stops it after.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest

from devices.base import DeviceError
from devices.keyboard import BINDINGS, KeyboardDevice, bindings_table
from tests.support import xdotool

DT = 1 / 30
POS, ROT = 0.2, 1.0


@pytest.fixture
def x_display(xvfb: str, monkeypatch: pytest.MonkeyPatch) -> str:
    monkeypatch.setenv("DISPLAY", xvfb)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.delenv("XDG_SESSION_TYPE", raising=False)
    return xvfb


@pytest.fixture
def kb(x_display: str) -> Iterator[KeyboardDevice]:
    device = KeyboardDevice(pos_speed=POS, rot_speed=ROT, n_arms=1)
    device.start()
    yield device
    close_and_join(device, x_display)


def close_and_join(device: KeyboardDevice, display: str) -> None:
    """Close, then wake pynput's X11 listener (it notices stop() at the next key event) and join it."""
    device.close()
    listener = device._listener
    for _ in range(20):
        if not listener.is_alive():
            break
        xdotool(display, "key", "Shift_L")  # bound to nothing
        listener.join(0.1)
    assert not listener.is_alive()


class View:
    """The part of a SessionView the keyboard reads."""

    def __init__(self, n_arms: int = 1) -> None:
        self.n_arms = n_arms


def run_loop(device: KeyboardDevice, script, view=None, tail: float = 0.25) -> tuple[list, dict]:
    """Poll at 30 Hz (paced by wall time) while `script(marks)` sends keys in a thread.

    Returns the commands of every tick and the times the script marked.
    """
    view = view or View()
    marks: dict = {}
    sender = threading.Thread(target=script, args=(marks,))
    ticks: list[list] = []
    device.poll(view, DT)  # drop anything from before the loop
    next_tick = time.monotonic()
    sender.start()
    end = None
    while end is None or time.monotonic() < end:
        next_tick += DT
        time.sleep(max(0.0, next_tick - time.monotonic()))
        ticks.append(device.poll(view, DT))
        if end is None and not sender.is_alive():
            end = time.monotonic() + tail
    sender.join()
    return ticks, marks


def total(ticks, what: str) -> np.ndarray:
    return sum((getattr(c, what) for cmds in ticks for c in cmds), np.zeros(3))


def hold(display: str, key: str, seconds: float):
    def script(marks):
        time.sleep(0.15)
        marks["down"] = xdotool(display, "keydown", key)
        time.sleep(seconds)
        marks["up"] = xdotool(display, "keyup", key)

    return script


def test_holding_w_moves_plus_x_at_speed_for_the_time_held(kb, x_display):
    ticks, marks = run_loop(kb, hold(x_display, "w", 0.6))
    held = marks["up"] - marks["down"]
    moved = total(ticks, "translation")
    assert moved[0] == pytest.approx(POS * held, rel=0.2)
    assert abs(moved[1]) < 1e-12 and abs(moved[2]) < 1e-12
    assert not np.any(total(ticks, "rotation"))
    # hold-to-move, not one jump: many ticks carry motion, each at most speed x dt
    moving = [c for cmds in ticks for c in cmds if np.any(c.translation)]
    assert len(moving) >= 0.5 * held / DT
    assert max(c.translation[0] for c in moving) <= POS * DT * 1.0001
    assert ticks[-3:] == [[], [], []]  # released: motion stops


def test_holding_f_moves_down_and_j_yaws_left(kb, x_display):
    ticks, marks = run_loop(kb, hold(x_display, "f", 0.4))
    moved = total(ticks, "translation")
    assert moved[2] == pytest.approx(-POS * (marks["up"] - marks["down"]), rel=0.2)
    ticks, marks = run_loop(kb, hold(x_display, "j", 0.4))
    turned = total(ticks, "rotation")
    assert turned[2] == pytest.approx(ROT * (marks["up"] - marks["down"]), rel=0.2)
    assert not np.any(total(ticks, "translation"))


def test_speed_up_key_scales_the_speed(kb, x_display):
    def script(marks):
        xdotool(x_display, "key", "equal")
        hold(x_display, "w", 0.4)(marks)

    ticks, marks = run_loop(kb, script)
    assert kb.speed_scale == pytest.approx(1.5)
    # The speed of each tick, not the distance over the wall-clock hold: a loaded machine delivers X's key events
    # late, which shortens the hold the device sees (test_holding_w_moves... checks distance against time)
    steps = [c.translation[0] for cmds in ticks for c in cmds if np.any(c.translation)]
    assert max(steps) == pytest.approx(1.5 * POS * DT, rel=1e-6)
    assert len(steps) >= 0.5 * (marks["up"] - marks["down"]) / DT


def test_gripper_toggles_once_per_press(kb, x_display):
    def script(marks):
        xdotool(x_display, "key", "space")
        time.sleep(0.2)
        xdotool(x_display, "key", "space")

    ticks, _ = run_loop(kb, script)
    grips = [c.gripper for cmds in ticks for c in cmds if c.gripper]
    assert grips == ["toggle", "toggle"]


def test_one_shot_keys_fire_their_events_once_each_in_order(kb, x_display):
    def script(marks):
        for key in ("b", "Return", "BackSpace", "n"):
            xdotool(x_display, "key", key)
            time.sleep(0.05)

    ticks, _ = run_loop(kb, script)
    events = [e for cmds in ticks for c in cmds for e in c.events]
    assert events == ["start", "save", "discard", "reset"]


def test_switch_arm_and_frame(kb, x_display):
    def script(marks):
        xdotool(x_display, "key", "Tab", "c")
        hold(x_display, "a", 0.2)(marks)

    ticks, _ = run_loop(kb, script, view=View(n_arms=2))
    moving = [c for cmds in ticks for c in cmds if np.any(c.translation)]
    assert moving and all(c.arm == 1 and c.frame == "ee" and c.translation[1] > 0 for c in moving)


def test_status_and_close(kb):
    assert kb.status() == "connected"
    kb.close()
    assert kb.status() == "closed"


def test_no_display_dead_display_and_wayland_only_are_one_line_errors(xvfb, monkeypatch):
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    with pytest.raises(DeviceError, match="no display") as err:
        KeyboardDevice().start()
    assert "\n" not in str(err.value)
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    with pytest.raises(DeviceError, match="Wayland"):
        KeyboardDevice().start()
    monkeypatch.delenv("WAYLAND_DISPLAY")
    dead = next(n for n in range(500, 600) if not os.path.exists(f"/tmp/.X11-unix/X{n}"))
    monkeypatch.setenv("DISPLAY", f":{dead}")
    with pytest.raises(DeviceError, match="cannot connect to X display") as err:
        KeyboardDevice().start()
    assert "\n" not in str(err.value)


def test_bindings_table_lists_every_action_once():
    actions = [b.action for b in BINDINGS]
    assert len(actions) == len(set(actions))
    keys = [k for b in BINDINGS for k in b.keys]
    assert len(keys) == len(set(keys))
    table = bindings_table()
    for needed in ("gripper", "reset", "start", "save", "discard", "switch arm", "switch frame", "speed up", "speed down"):
        assert needed in table


def test_under_wayland_with_xwayland_the_keyboard_starts_with_a_caveat(x_display, monkeypatch):
    monkeypatch.setenv("WAYLAND_DISPLAY", "wayland-0")
    device = KeyboardDevice()
    device.start()
    try:
        assert device.status() == "connected"
        assert "Wayland" in device.warning and "\n" not in device.warning
    finally:
        close_and_join(device, x_display)


def test_key_state_counts_held_time_per_tick_and_ignores_autorepeat():
    from devices.keyboard import KeyState

    state = KeyState(now=0.0)
    state.press("w", 0.010)
    state.press("w", 0.020)  # autorepeat: no new press, no restart
    held, presses = state.take(0.040)
    assert held == {"w": pytest.approx(0.75)} and presses == ["w"]
    state.release("w", 0.050)
    state.press("space", 0.060)
    state.release("space", 0.070)
    held, presses = state.take(0.080)  # w held 10 of 40 ms; the tap counts too
    assert held["w"] == pytest.approx(0.25) and held["space"] == pytest.approx(0.25) and presses == ["space"]
    state.press("space", 0.085)  # X11 autorepeat as release+press pairs: not a new press
    state.release("space", 0.100)
    state.press("space", 0.100 + 0.01)
    _, presses = state.take(0.2)
    assert presses == []
    held, _ = state.take(0.3)
    assert held == {"space": pytest.approx(1.0)}  # still down


def test_keys_with_ctrl_or_alt_belong_to_other_apps(kb, x_display):
    def script(marks):
        for combo in ("ctrl+w", "ctrl+Return", "alt+space", "ctrl+n"):
            xdotool(x_display, "key", combo)
        time.sleep(0.1)
        xdotool(x_display, "key", "space")  # modifiers released: keys count again

    ticks, _ = run_loop(kb, script)
    commands = [c for cmds in ticks for c in cmds]
    assert [c.gripper for c in commands] == ["toggle"]
    assert not any(c.events for c in commands) and not any(np.any(c.translation) for c in commands)
