"""The XR page in headless Chromium with Meta's WebXR emulator (IWER, an emulated Quest 3), against `teleop serve`.

IWER (npm `iwer` 2.5.0, `build/iwer.min.js`) is fetched by `./run.sh test` into ~/.cache/mujoco-teleop/iwer
(or $TELEOP_IWER_CACHE), never committed; without it these tests fail naming the command that fetches it.
It is injected before the page loads; the tests move its controllers (`position`, `quaternion`,
`updateButtonValue`) as an operator would and read what the session did (its status file, the saved
episode). One served session and one page in VR are shared by the module (SwiftShader is slow on 2 cores):
the tests run in file order on that page, each from where the last left the arm; the two-arm rig's test, last,
closes them before it opens its own (one VR page drawing at a time).
"""

from __future__ import annotations

import io
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest

import tests.browser as headless
from replay import load_episode

pytestmark = pytest.mark.browser
IWER_VERSION = "2.5.0"
VIEWPORT = {"width": 360, "height": 180}  # the emulated headset's canvas: both eyes side by side
STEP_M = 0.005  # a hand moves in steps this long, each applied before the next (a slow page's frames come late)


# Every requestAnimationFrame callback of the page runs EVERY (3) display frames after it was asked for, so a loop that
# asks again each frame (IWER's device frames, hence the page's XR frames) runs at a third of the browser's 60 Hz.
# SwiftShader's drawing is CPU the suite's other workers need (the page in VR and idle, the 2-core machine: 37 frames
# a second uncapped took 1.05 CPU s a second of Chromium, 19 at 20 Hz 0.69; this file's run went from 133 s and 154
# CPU s of Chromium to 70 s and 52). Nothing here counts on the rate: `Headset.frames` waits for frames by number.
# cancelAnimationFrame still cancels, at any stage.
EVERY = 3
SLOWER_FRAMES = """
(() => {
  const raf = window.requestAnimationFrame.bind(window), caf = window.cancelAnimationFrame.bind(window);
  const pending = new Map();
  let last = 0;
  const later = (id, frames, callback) => raf((t) => {
    if (frames > 1) pending.set(id, later(id, frames - 1, callback));
    else { pending.delete(id); callback(t); }
  });
  window.requestAnimationFrame = (callback) => { const id = ++last; pending.set(id, later(id, EVERY, callback)); return id; };
  window.cancelAnimationFrame = (id) => { if (pending.has(id)) { caf(pending.get(id)); pending.delete(id); } };
})();
""".replace("EVERY", str(EVERY))


def iwer_script() -> str:
    """IWER's UMD build and its install as a Quest 3 with two eyes (window.__iwer), or an error naming the fetch;
    the page's frames slowed (SLOWER_FRAMES)."""
    cache = Path(os.environ.get("TELEOP_IWER_CACHE", Path.home() / ".cache" / "mujoco-teleop" / "iwer"))
    path = cache / IWER_VERSION / "package" / "build" / "iwer.min.js"
    if not path.is_file():
        raise FileNotFoundError(f"IWER {IWER_VERSION} (the WebXR emulator) is not at {path}: `./run.sh test` fetches it, "
                                f"or: mkdir -p {path.parents[2]} && cd {path.parents[2]} && npm pack iwer@{IWER_VERSION} "
                                f"&& tar xzf iwer-{IWER_VERSION}.tgz")
    return SLOWER_FRAMES + path.read_text(encoding="utf-8") + (
        "\n;(() => { const d = new IWER.XRDevice(IWER.metaQuest3, {stereoEnabled: true});"
        " d.installRuntime({forceInstall: true}); window.__iwer = d; })();\n")


def open_headset(browser, url: str, init: str = ""):
    """The XR page with an emulated Quest 3, in VR and drawing."""
    page = browser.new_page(viewport=VIEWPORT)
    page.add_init_script(iwer_script() + init)
    page.goto(url, timeout=60000)
    page.wait_for_function("window.__xr && window.__xr.scenesReceived > 0", timeout=60000)
    page.get_by_text("Enter VR", exact=True).click()
    page.wait_for_function("window.__xr.drawnFrames > 2 && window.__xr.posesReceived > 2", timeout=60000)
    return page


class Headset:
    """One emulated headset's controllers, moved in small applied steps."""

    def __init__(self, page, served) -> None:
        self.page, self.served = page, served
        self.inputs = "controllers"  # or "hands" (IWER's primaryInputMode 'hand': the clutch is a pose, CLUTCH_POSE)

    def clutch(self, side: str, on: bool) -> None:
        if self.inputs == "hands":
            self.page.evaluate(f"window.__iwer.hands.{side}.poseId = '{'clutch' if on else 'default'}'")
            self.frames()
        else:
            self.button(side, "squeeze", 1 if on else 0)

    def frames(self, n: int = 2) -> None:
        """Wait until the page has run `n` more XR frames (what was set is then read and sent)."""
        now = self.page.evaluate("window.__xr.frame")
        self.page.wait_for_function(f"window.__xr.frame >= {now + n}", timeout=30000)

    def button(self, side: str, name: str, value: float) -> None:
        self.page.evaluate(f"window.__iwer.controllers.{side}.updateButtonValue('{name}', {value})")
        self.frames()

    def press(self, side: str, name: str) -> None:
        self.button(side, name, 1)
        self.button(side, name, 0)

    def position(self, side: str) -> np.ndarray:
        return np.array(self.page.evaluate(f"(() => {{ const p = window.__iwer.{self.inputs}.{side}.position; return [p.x, p.y, p.z]; }})()"))

    def applied(self, side: str) -> None:
        """Wait until the server applied this hand's newest sent pose (its frame echoed in a poses message), when engaged."""
        frame = self.page.evaluate(f"window.__xr.hands.{side}.last ? window.__xr.hands.{side}.last.frame : -1")
        self.page.wait_for_function(f"window.__xr.appliedFrame >= {frame}", timeout=30000)

    def _target(self, arm: int) -> np.ndarray:
        status = self.served.wait_for(lambda s: True, what="status")
        tick = status["tick"]
        status = self.served.wait_for(lambda s: s["tick"] >= tick + 3, what="three ticks")  # the status file lags a tick
        return np.array([*status["target_pos"][arm], *status["target_quat"][arm]])

    def _step(self, side: str, arm: int, go, back, before: np.ndarray | None = None) -> np.ndarray:
        """One engaged step of the hand (`go`), applied; returns the arm's target after it. A step lost to a clutch
        let go by a late frame (the machine too loaded to draw for 0.25 s: the safety rule) is done again from where
        it started, the clutch up. `before`: the target the last step of this move left (the hand has not moved
        since, so nothing else moved the target), read from the status when not given."""
        for _ in range(4):
            if before is None:
                before = self._target(arm)
            go()
            self.frames()
            self.applied(side)
            after = self._target(arm)
            if not np.allclose(after, before, atol=1e-7):
                return after
            self.clutch(side, False)
            back()
            self.frames()
            self.clutch(side, True)
            self.frames()
        raise AssertionError("a step of the hand was lost four times")

    def move(self, side: str, delta, engaged: bool = True, arm: int = 0, step_m: float = STEP_M) -> None:
        """Move a controller by `delta` (m, WebXR's local-floor: -z forward) in steps of `step_m`."""
        delta = np.asarray(delta, dtype=float)
        steps = max(1, int(math.ceil(np.linalg.norm(delta) / step_m)))
        target = None
        for _ in range(steps):
            start = self.position(side)
            go = self._setter(side, start + delta / steps)
            if engaged:
                target = self._step(side, arm, go, self._setter(side, start), target)
            else:
                go()
                self.frames()

    def _setter(self, side: str, where):
        x, y, z = (float(v) for v in where)
        return lambda: self.page.evaluate(f"window.__iwer.{self.inputs}.{side}.position.set({x}, {y}, {z})")

    def turn(self, side: str, axis, degrees: float, steps: int = 10, arm: int = 0) -> None:
        """Turn a controller from no rotation about `axis` (local-floor) by `degrees` in steps, each applied."""
        axis = np.asarray(axis, dtype=float) / np.linalg.norm(axis)

        def rotation(k: int):
            half = math.radians(degrees) * k / steps / 2
            x, y, z = axis * math.sin(half)
            return lambda: self.page.evaluate(f"window.__iwer.controllers.{side}.quaternion.set({x}, {y}, {z}, {math.cos(half)})")

        target = None
        for k in range(1, steps + 1):
            target = self._step(side, arm, rotation(k), rotation(k - 1), target)

    def settled(self, arm: int = 0) -> dict:
        """The status once the arm's target stays put for a few ticks."""
        last = None
        deadline = time.monotonic() + 20.0
        while time.monotonic() < deadline:
            status = self.served.wait_for(lambda s: s.get("tick", 0) > (last or {}).get("tick", 0) + 6, what="ticks")
            if last is not None and np.allclose(status["target_pos"][arm], last["target_pos"][arm], atol=1e-9):
                return status
            last = status
        raise AssertionError("the target kept moving")


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    work = tmp_path_factory.mktemp("xr")
    proc = headless.ServeProcess(["--record", str(work / "eps"), "--device", "gizmo"], work)
    yield proc
    proc.stop()


# What the one-arm headset holds open (its page in VR, its served session): the two-arm rig, last in the file,
# closes them first, so that one VR page at a time draws (SwiftShader: a VR page keeps a core busy drawing).
ONE_ARM: list = []


@pytest.fixture(scope="module")
def headset(browser, served):
    page = open_headset(browser, served.url + "/xr")
    ONE_ARM.append((page, served))
    yield Headset(page, served)
    page.close()


def _angle(q1, q2) -> float:
    """Degrees between two wxyz rotations."""
    return math.degrees(2 * math.acos(min(1.0, abs(float(np.dot(q1, q2))))))


def test_the_page_draws_the_robot_and_the_table_in_both_eyes(headset):
    from PIL import Image

    headset.frames(3)
    shot = np.asarray(Image.open(io.BytesIO(headset.page.screenshot())).convert("RGB")).astype(float) / 255.0
    scene = headset.page.evaluate("window.__xr.scene.draws.map((d) => d.color)")
    table = np.array([0.62, 0.5, 0.38])
    assert any(np.allclose(c[:3], table, atol=0.01) for c in scene)
    for eye in (shot[:, :VIEWPORT["width"] // 2], shot[:, VIEWPORT["width"] // 2:]):
        chroma = eye / np.maximum(eye.sum(axis=2, keepdims=True), 1e-6)
        wood = np.all(np.abs(chroma - table / table.sum()) < 0.02, axis=2) & (eye.sum(axis=2) > 0.3)
        light = np.all(eye > 0.75, axis=2) & (np.ptp(eye, axis=2) < 0.05)  # the arm's white links (lit)
        assert wood.mean() > 0.1, f"the table covers {wood.mean():.1%} of an eye"
        assert light.mean() > 0.02, f"the arm covers {light.mean():.1%} of an eye"
    left, right = shot[:, :VIEWPORT["width"] // 2], shot[:, VIEWPORT["width"] // 2:]
    assert not np.array_equal(left, right), "two eyes, two views (the IPD apart)"


def test_a_squeeze_move_turn_and_trigger_are_recorded_and_replay_bit_for_bit(headset, served):
    h = headset
    h.press("right", "a-button")  # A: start recording
    served.wait_for(lambda s: s["recording"], what="recording")
    h.settled()
    h.button("right", "squeeze", 1)
    h.move("right", [0, 0, -0.10])  # 10 cm forward
    h.button("right", "squeeze", 0)
    moved = h.settled()
    h.move("right", [0, 0, 0.10], engaged=False)  # back, with the clutch up
    held = h.settled()
    assert np.allclose(held["target_pos"][0], moved["target_pos"][0], atol=1e-9), "an arm whose clutch is up never moves"
    h.button("right", "squeeze", 1)
    h.turn("right", [0, 0, -1], 90)  # a wrist turn about where the hand points
    h.button("right", "squeeze", 0)
    turned = h.settled()
    assert _angle(turned["target_quat"][0], held["target_quat"][0]) == pytest.approx(90, abs=5), turned["xr"]
    h.button("right", "trigger", 0.5)  # half pressed: half open
    served.wait_for(lambda s: s["xr"]["poses"] > turned["xr"]["poses"] + 3, what="poses")
    h.settled()
    h.press("right", "a-button")  # A again: save
    saved = served.wait_for(lambda s: s["episodes_saved"] == 1 and any(v is not None for v in s["verified"].values()),
                            timeout_s=120, what="saved and checked by exact replay")
    path = saved["saved_files"][-1]
    assert saved["verified"][path] is True, "the episode replays bit for bit"
    episode = load_episode(path)
    assert "xr" in episode.meta.devices
    commands = [c for step in episode.commands for c in step if c.get("source") == "xr"]
    assert any(c["target_pos"] is not None for c in commands) and all(c["arm"] == 0 for c in commands)
    assert any(c["gripper_opening"] is not None and abs(c["gripper_opening"] - 0.5) < 0.01 for c in commands)
    # the recorded EE: from the start to the end of the stretch held at the moved target, 10 cm forward (+x)
    target = episode.ee_target[:, 0, :3]
    at = np.flatnonzero(np.all(np.abs(target - moved["target_pos"][0]) < 1e-5, axis=1))
    assert at.size, "the moved target is in the episode"
    run_end = at[0] + int(np.argmax(np.diff(np.append(at - at[0], -1)) != 1))  # the last step of the first unbroken stretch
    d = episode.ee_pose[run_end, 0, :3] - episode.ee_pose[0, 0, :3]
    assert d[0] == pytest.approx(0.10, abs=0.015) and abs(d[1]) < 0.015 and abs(d[2]) < 0.015, f"EE moved {d}: {moved['xr']}"


def test_b_discards_the_episode(headset, served):
    before = served.status()
    headset.press("right", "a-button")
    served.wait_for(lambda s: s["recording"], what="recording")
    headset.press("right", "b-button")
    after = served.wait_for(lambda s: s["episodes_discarded"] == before["episodes_discarded"] + 1 and not s["recording"],
                            what="discarded")
    assert after["episodes_saved"] == before["episodes_saved"]


def test_tracking_loss_the_system_menu_and_a_nan_pose_let_go_and_hold_the_arm(headset, served):
    h = headset
    h.button("right", "squeeze", 1)
    h.move("right", [0, 0, -0.01])
    engaged = served.wait_for(lambda s: s["xr"]["engaged"]["right"], what="engaged")
    # tracking lost mid-squeeze: the controller moves while lost; the arm holds
    h.page.evaluate("window.__iwer.controllers.right.connected = false")
    lost = served.wait_for(lambda s: s["xr"]["releases"].get("tracking lost", 0) >= 1, what="released on tracking loss")
    h.move("right", [0, 0, -0.03], engaged=False)
    h.page.evaluate("window.__iwer.controllers.right.connected = true")
    back = served.wait_for(lambda s: s["xr"]["engaged"]["right"] and s["tick"] > lost["tick"] + 5, what="taken again")
    assert np.allclose(back["target_pos"][0], lost["target_pos"][0], atol=1e-3), "no jump when tracking comes back"
    # the system menu (visible-blurred)
    h.page.evaluate("window.__iwer.updateVisibilityState('visible-blurred')")
    blurred = served.wait_for(lambda s: s["xr"]["releases"].get("blurred", 0) >= 1 and not s["xr"]["engaged"]["right"],
                              what="released on visible-blurred")
    h.move("right", [0, 0, -0.03], engaged=False)
    h.page.evaluate("window.__iwer.updateVisibilityState('visible')")
    h.frames(3)
    # a NaN pose: dropped, counted, never applied
    h.page.evaluate("window.__iwer.controllers.right.position.set(NaN, 1.5, -0.4)")
    nan = served.wait_for(lambda s: s["xr"]["bad_poses"] >= 1, what="the NaN pose counted")
    h.page.evaluate("window.__iwer.controllers.right.position.set(0.25, 1.5, -0.45)")
    h.frames(3)
    h.button("right", "squeeze", 0)
    final = h.settled()
    assert np.isfinite(final["target_pos"][0]).all() and final["ik_error_mm"][0] < 50
    assert np.allclose(final["target_pos"][0], blurred["target_pos"][0], atol=2e-3), "held through all of it"
    assert nan["xr"]["releases"].get("bad pose", 0) >= 1 and engaged["xr"]["jumps"] == 0


PULSE_SPY = """
(() => {
  const source = [...window.__xr.session.inputSources].find((s) => s.handedness === 'right');
  const proto = Object.getPrototypeOf(source.gamepad.hapticActuators[0]);
  if (proto.__spied) return;
  const pulse = proto.pulse;
  window.__pulses = [];
  proto.pulse = function (value, ms) { window.__pulses.push([value, ms]); return pulse.call(this, value, ms); };
  proto.__spied = true;
})();
"""


def test_the_controller_pulses_while_the_fingers_touch_the_cube_and_not_while_they_close_on_air(headset, served):
    h = headset
    h.page.evaluate(PULSE_SPY)
    h.button("right", "trigger", 1)  # close on air, far above the cube
    served.wait_for(lambda s: not s["gripper_open"][0], what="closed")
    h.frames(20)
    assert h.page.evaluate("window.__pulses.length") == 0 and max(h.page.evaluate("window.__xr.forces")) < 0.5
    h.button("right", "trigger", 0)
    served.wait_for(lambda s: s["gripper_open"][0], what="open")
    status = h.settled()
    cube, ee = np.array(status["objects"]["cube"]), np.array(status["ee_pos"][0])
    to = cube + [0, 0, 0.005] - ee  # world: x forward, y left, z up -> local-floor: -z, -x, +y
    h.button("right", "squeeze", 1)
    h.move("right", [-to[1], 0, -to[0]], step_m=0.02)
    h.move("right", [0, to[2], 0], step_m=0.02)
    h.button("right", "squeeze", 0)
    h.settled()
    h.page.evaluate("window.__pulses.length = 0")
    h.button("right", "trigger", 1)  # close on the cube
    h.page.wait_for_function("window.__pulses.length >= 3", timeout=60000)
    pulses = h.page.evaluate("window.__pulses")
    assert all(0 < value <= 1 and ms > 0 for value, ms in pulses)
    assert max(h.page.evaluate("window.__xr.forces")) > 0.5
    h.button("right", "trigger", 0)


# IWER's hands have a default and a thumb-index pinch pose; a third pose with the middle finger's tip on the
# thumb's (the clutch) is added to the right hand's poses (kept under one of its private symbols: found by shape).
CLUTCH_POSE = """
(() => {
  const hand = window.__iwer.hands.right;
  const store = Object.getOwnPropertySymbols(hand).map((k) => hand[k]).find((v) => v && v.poses && v.poses.default);
  const base = store.poses.default, joints = { ...base.jointTransforms };
  joints['middle-finger-tip'] = { ...joints['thumb-tip'], offsetMatrix: joints['thumb-tip'].offsetMatrix.slice() };
  store.poses.clutch = { ...base, jointTransforms: joints };
})();
"""


def test_tracked_hands_pinch_the_gripper_and_a_hand_lost_mid_clutch_holds_the_arm(headset, served):
    h = headset
    h.page.evaluate(CLUTCH_POSE)
    h.page.evaluate("window.__iwer.primaryInputMode = 'hand'")
    h.page.wait_for_function("window.__xr.hands.right.last && window.__xr.hands.right.last.mode === 'hand'", timeout=30000)
    h.page.evaluate("window.__iwer.hands.right.updatePinchValue(1)")  # thumb and index together: closed
    served.wait_for(lambda s: not s["gripper_open"][0], what="closed by the pinch")
    h.page.evaluate("window.__iwer.hands.right.updatePinchValue(0)")
    served.wait_for(lambda s: s["gripper_open"][0], what="opened")
    before = h.settled()
    h.inputs = "hands"
    try:
        h.clutch("right", True)  # middle finger on the thumb: the clutch
        h.move("right", [0, 0.02, 0])  # 2 cm up
    finally:
        h.inputs = "controllers"
    moved = h.settled()
    assert np.array(moved["target_pos"][0])[2] - np.array(before["target_pos"][0])[2] == pytest.approx(0.02, abs=0.005)
    h.page.evaluate("window.__iwer.hands.right.connected = false")  # the hand lost mid-clutch
    lost = served.wait_for(lambda s: s["xr"]["releases"].get("tracking lost", 0) > moved["xr"]["releases"].get("tracking lost", 0),
                           what="released")
    h.page.evaluate("(() => { const p = window.__iwer.hands.right.position; p.set(p.x, p.y + 0.05, p.z); })()")
    h.frames(5)
    held = h.settled()
    assert np.allclose(held["target_pos"][0], lost["target_pos"][0], atol=1e-9) and not held["xr"]["engaged"]["right"]
    h.page.evaluate("window.__iwer.hands.right.poseId = 'default'; window.__iwer.hands.right.connected = true;"
                    " window.__iwer.primaryInputMode = 'controller'")
    h.frames(3)


@pytest.fixture(scope="module")
def rig(browser, tmp_path_factory):
    while ONE_ARM:  # page.close() and ServeProcess.stop() may be called again (the fixtures' teardown does)
        page, served = ONE_ARM.pop()
        page.close()
        served.stop()
    work = tmp_path_factory.mktemp("xr-rig")
    proc = headless.ServeProcess(["--scene", "handover", "--robot", "bimanual", "--device", "gizmo"], work)
    page = open_headset(browser, proc.url + "/xr")
    yield Headset(page, proc)
    page.close()
    proc.stop()


def test_on_the_two_arm_rig_each_controller_moves_its_own_arm_only(rig):
    for side, arm in (("left", 0), ("right", 1)):
        before = rig.settled(arm)
        rig.button(side, "squeeze", 1)
        rig.move(side, [0, 0, -0.03], arm=arm)  # 3 cm forward: towards the table, across the arms' line
        rig.button(side, "squeeze", 0)
        after = rig.settled(arm)
        other = 1 - arm
        moved = np.array(after["target_pos"][arm]) - np.array(before["target_pos"][arm])
        assert np.linalg.norm(moved) == pytest.approx(0.03, abs=0.005), moved
        assert np.allclose(after["target_pos"][other], before["target_pos"][other], atol=1e-9), "the other arm stays"
