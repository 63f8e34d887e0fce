"""Devices in the operator's browser, end to end in headless Chromium: a gamepad (navigator.getGamepads
defined by an init script), a SpaceMouse over WebHID (navigator.hid defined the same way, fed real
report bytes), and the phone page (scripted DeviceOrientation events and a held clutch)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

import tests.browser as headless
from devices.spacemouse_protocol import encode_buttons, encode_combined

GAMEPAD = r"""
window.__pad = {axes: [0, 0, 0, 0], buttons: new Array(17).fill(0), connected: true};
navigator.getGamepads = () => [window.__pad.connected ? {
  id: "Xbox Wireless Controller (STANDARD GAMEPAD Vendor: 045e Product: 0b13)", index: 0, connected: true,
  mapping: "standard", timestamp: performance.now(), axes: window.__pad.axes.slice(),
  buttons: window.__pad.buttons.map((v) => ({pressed: v > 0.5, touched: v > 0, value: v})),
} : null];
"""

WEBHID = r"""
(() => {
  const device = new EventTarget();
  device.opened = false;
  device.productName = "SpaceMouse Compact";
  device.vendorId = 0x256f;
  device.productId = 0xc635;
  device.open = async () => { device.opened = true; };
  window.__hidDevice = device;
  window.__hidReport = (bytes) => {
    const event = new Event("inputreport");
    event.reportId = bytes[0];
    event.data = new DataView(new Uint8Array(bytes.slice(1)).buffer);
    event.device = device;
    device.dispatchEvent(event);
  };
  const hid = new EventTarget();
  hid.getDevices = async () => (window.__hidGranted ? [device] : []);
  hid.requestDevice = async () => { window.__hidGranted = true; return [device]; };
  Object.defineProperty(navigator, "hid", {value: hid});
})();
"""


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    work = tmp_path_factory.mktemp("page-devices")
    proc = headless.ServeProcess(["--record", str(work / "eps"), "--device", "gizmo,gamepad,phone,webhid"], work)
    yield proc
    proc.stop()


def _page(browser, server, init: str):
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.add_init_script(init)
    page.goto(server.url, timeout=60000)
    page.wait_for_selector("canvas", timeout=60000)
    headless.dismiss_toasts(page)
    return page


def _target(server) -> np.ndarray:
    return np.array(server.status()["target_pos"][0])


def _settled(server, timeout_s: float = 10.0) -> np.ndarray:
    """The target once it stays put for 0.6 s (software WebGL can stall the page's timers for a second or two)."""
    deadline = time.monotonic() + timeout_s
    last = _target(server)
    while time.monotonic() < deadline:
        time.sleep(0.6)
        now = _target(server)
        if np.allclose(now, last, atol=1e-9):
            return now
        last = now
    raise AssertionError(f"the target kept moving for {timeout_s} s")


def test_a_gamepad_in_the_page_drives_the_arm_and_presses_the_episode_buttons(browser, server):
    page = _page(browser, server, GAMEPAD)
    try:
        server.wait_for(lambda s: "Xbox" in s["devices"]["gamepad"], what="the pad to reach the server")
        start = _target(server)
        page.evaluate("window.__pad.axes[1] = -1")  # left stick fully up: +x, away from the base
        moved = server.wait_for(lambda s: s["target_pos"][0][0] > start[0] + 0.03, what="the stick to move +x")
        page.evaluate("window.__pad.axes[1] = 0")
        settled = _settled(server)  # released: it stops (once the page's next state arrives)
        assert abs(settled[1] - start[1]) < 0.01 and abs(settled[2] - start[2]) < 0.01 and not moved["recording"]

        def press(button: int, effect, what: str) -> None:
            """Hold `button` until its effect shows, then release it until the page has sent the release
            (the page samples the pad on its own timer, which software WebGL can stall)."""
            page.evaluate(f"window.__pad.buttons[{button}] = 1")
            server.wait_for(effect, what=what)
            page.evaluate(f"window.__pad.buttons[{button}] = 0")
            sent = server.status()["input"]["accepted"]
            server.wait_for(lambda s: s["input"]["accepted"] >= sent + 2, what="the release to be sent")

        saved = server.status()["episodes_saved"]
        press(9, lambda s: s["recording"], "Start to begin recording")
        press(0, lambda s: s["gripper_open"] == [False], "A to close the gripper")
        press(9, lambda s: not s["recording"] and s["episodes_saved"] == saved + 1, "Start to stop and save")
        press(1, lambda s: s["seed"] == 1, "B to reset the scene")
        page.evaluate("window.__pad.connected = false")
        server.wait_for(lambda s: "no pad" in s["devices"]["gamepad"], what="the pad to be let go")
    finally:
        page.close()


def test_a_webhid_spacemouse_in_the_page_moves_the_arm(browser, server):
    page = _page(browser, server, WEBHID)
    try:
        headless.click_button(page, "Connect SpaceMouse")
        server.wait_for(lambda s: "SpaceMouse Compact in a browser" in s["devices"]["webhid-spacemouse"],
                        what="the WebHID device to connect")
        start = _target(server)
        push = list(encode_combined(0, -350, 0, 0, 0, 0))  # y toward the operator... pushed away: -y in HID
        page.evaluate(f"window.__hidReport({json.dumps(push)})")  # held until the target has moved, not for a set time
        moved = server.wait_for(lambda s: np.linalg.norm(np.array(s["target_pos"][0]) - start) > 0.03, timeout_s=60,
                                what="the reports to move the target")
        page.evaluate(f"window.__hidReport({json.dumps(list(encode_combined(0, 0, 0, 0, 0, 0)))})")
        delta = np.array(moved["target_pos"][0]) - start
        assert delta[0] > 0.03 and abs(delta[1]) < 0.01  # pushed away from the operator (behind the robot): +x
        _settled(server)  # the zero report stopped it
        button = list(encode_buttons(1))
        page.evaluate(f"window.__hidReport({json.dumps(button)})")  # left button: the gripper
        server.wait_for(lambda s: s["gripper_open"] == [False], what="the left button to close the gripper")
        page.evaluate(f"window.__hidReport({json.dumps(list(encode_buttons(0)))})")
    finally:
        page.close()


def _yaw(q) -> float:
    w, x, y, z = q
    return float(np.degrees(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))))


def test_the_phone_page_moves_the_target_only_while_the_clutch_is_held(browser, server):
    page = browser.new_page(viewport={"width": 400, "height": 800}, has_touch=False)
    page.goto(server.url + "/phone", timeout=60000)
    try:
        page.wait_for_function("window.__teleopPhone !== undefined", timeout=60000)

        def orient(alpha: float) -> None:
            page.evaluate(f"window.dispatchEvent(new DeviceOrientationEvent('deviceorientation', "
                          f"{{alpha: {alpha}, beta: 0, gamma: 0, absolute: true}}))")

        def connected(status: dict) -> bool:  # an orientation sent before the page's channel opened is not seen: send again
            if "phone (orientation)" in status["devices"]["phone"]:
                return True
            orient(90)
            return False

        server.wait_for(connected, timeout_s=120, what="the phone to connect")
        start = server.status()["target_quat"][0]
        orient(120)  # turned, clutch up: nothing
        time.sleep(0.4)
        assert _yaw(server.status()["target_quat"][0]) == pytest.approx(_yaw(start), abs=0.1)

        box = page.locator("#clutch").bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        orient(120)
        time.sleep(0.3)
        for alpha in range(121, 151, 3):  # 30 degrees more with the clutch held
            orient(alpha)
            time.sleep(0.03)
        orient(150)
        turned = server.wait_for(lambda s: abs(_yaw(s["target_quat"][0]) - _yaw(start) - 30) < 2,
                                 what="the held clutch to turn the target")
        page.mouse.up()
        time.sleep(0.3)
        orient(90)  # back, clutch up
        time.sleep(0.4)
        assert _yaw(server.status()["target_quat"][0]) == pytest.approx(_yaw(turned["target_quat"][0]), abs=0.5)
        was = server.status()["gripper_open"][0]
        page.locator("#gripper").click()
        server.wait_for(lambda s: s["gripper_open"] == [not was], what="the phone's gripper button")
    finally:
        page.close()


FAKE_XR = r"""
(() => {  // WebXR as a phone's AR browser has it: the viewer's pose each frame, from window.__xrPose
  window.__xrPose = {p: [0.0, 1.4, 0.0], q: [0.0, 0.0, 0.0, 1.0]};
  const session = new EventTarget();
  session.requestReferenceSpace = async () => ({});
  session.requestAnimationFrame = (callback) => setTimeout(() => callback(performance.now(), {
    getViewerPose: () => {
      const [x, y, z] = window.__xrPose.p, [qx, qy, qz, qw] = window.__xrPose.q;
      return {transform: {position: {x, y, z}, orientation: {x: qx, y: qy, z: qz, w: qw}}};
    },
  }), 16);
  const xr = {isSessionSupported: async (mode) => mode === "immersive-ar", requestSession: async () => session};
  Object.defineProperty(navigator, "xr", {value: xr});
})();
"""


def test_the_phone_page_uses_webxr_position_where_the_browser_has_it(browser, server):
    """With WebXR the phone's motion (not only its turn) moves the target, metre for metre, clutch held only."""
    page = browser.new_page(viewport={"width": 400, "height": 800}, has_touch=False)
    page.add_init_script(FAKE_XR)
    page.goto(server.url + "/phone", timeout=60000)
    try:
        page.locator("#xr").wait_for(state="visible", timeout=60000)  # offered only where AR is supported
        page.locator("#xr").click()
        server.wait_for(lambda s: "phone (WebXR)" in s["devices"]["phone"], what="the phone on WebXR")
        start = _settled(server)
        page.evaluate("window.__xrPose.p = [0.0, 1.5, -0.2]")  # moved with the clutch up: nothing
        time.sleep(0.5)
        np.testing.assert_allclose(_target(server), start, atol=1e-6)

        box = page.locator("#clutch").bounding_box()
        page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
        page.mouse.down()
        time.sleep(0.3)
        for k in range(1, 11):  # 5 cm forward (XR's -z) and 3 cm up (XR's +y), in steps
            page.evaluate(f"window.__xrPose.p = [0.0, {1.5 + 0.003 * k}, {-0.2 - 0.005 * k}]")
            time.sleep(0.05)
        def shift(status) -> tuple[float, float]:  # (horizontal, vertical) motion of the target since the start
            delta = np.array(status["target_pos"][0]) - start
            return float(np.hypot(delta[0], delta[1])), float(delta[2])

        # the whole motion, forward turned to the robot's frame, metre for metre: 5 cm along, 3 cm up
        server.wait_for(lambda s: np.allclose(shift(s), (0.05, 0.03), atol=5e-4),
                        what="the held clutch to move the target 5 cm along and 3 cm up")
        page.mouse.up()
        time.sleep(0.3)
        after = _settled(server)
        page.evaluate("window.__xrPose.p = [0.3, 1.2, 0.4]")  # clutch up again: nothing
        time.sleep(0.5)
        np.testing.assert_allclose(_target(server), after, atol=1e-6)
    finally:
        page.close()
