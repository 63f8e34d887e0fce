"""Keys typed in the page drive the arm: headless Chromium (Playwright) against `teleop serve`.

The server runs with `--device gizmo,keyboard` and no X display, so this
machine's keyboard cannot start and the keys come only from the page (the
`page keyboard` device). Software WebGL keeps the page's main thread busy:
on a loaded machine a key event waits up to half a second for a frame to
finish before the page handles it. So the hold test times the hold where the
page handles the keys (a listener beside the page's own, in the same phase),
and checks that this lies within what Playwright's calls allow.
"""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np
import pytest
from websockets.asyncio.client import connect

from teleop.web.shared.input_channel import PATH, QUIET_S
from tests import browser as headless

PAGE_SIZE = (480, 320)  # software WebGL: the fewer pixels, the sooner the page handles a key
POS_SPEED = 0.05  # m/s: a 2 s hold stays well within the arm's reach from home


@pytest.fixture(scope="module")
def record_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("episodes")


@pytest.fixture(scope="module")
def server(record_dir, tmp_path_factory):
    proc = headless.ServeProcess(["--device", "gizmo,keyboard", "--pos-speed", str(POS_SPEED), "--record", str(record_dir)],
                                 tmp_path_factory.mktemp("serve"), env={"DISPLAY": "", "WAYLAND_DISPLAY": ""})
    yield proc
    proc.stop()


def open_keyboard_page(browser, server):
    """A page (in a context of its own) whose key script has connected to the input channel."""
    context = browser.new_context(viewport={"width": PAGE_SIZE[0], "height": PAGE_SIZE[1]})
    page = context.new_page()
    page.goto(server.url, timeout=60000)
    page.wait_for_selector("canvas", timeout=60000)
    page.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60000)
    headless.dismiss_toasts(page)
    for _ in range(40):  # the first input events wait for the first frames (shader compiles): warm up
        start = time.monotonic()
        page.keyboard.press("Shift")
        if time.monotonic() - start < 0.15:
            break
    return page


@pytest.fixture(scope="module")
def page(server, browser):
    page = open_keyboard_page(browser, server)
    yield page
    page.context.close()


def target(status: dict) -> np.ndarray:
    return np.array(status["target_pos"][0])


def settled(server, what: str, timeout_s: float = 20.0) -> dict:
    """The status once no page key is held and the target has stopped moving."""
    server.wait_for(lambda s: not s["page_keyboard"]["held"], timeout_s=timeout_s, what=what)
    deadline = time.monotonic() + timeout_s
    previous = target(server.status())
    while time.monotonic() < deadline:
        time.sleep(0.3)
        status = server.status()
        if np.allclose(target(status), previous, atol=1e-6):
            return status
        previous = target(status)
    raise TimeoutError(f"the target kept moving: {what}")


KEY_TIMES = """() => {
  if (!window.__keyTimes) {
    const note = (e) => { if (!e.repeat) window.__keyTimes.push([e.type, e.key, performance.now()]); };
    window.addEventListener("keydown", note, true);  // after the page's own listener, in the same phase
    window.addEventListener("keyup", note, true);
  }
  window.__keyTimes = [];
}"""


def hold(page, key: str, seconds: float, repeat_every: float = 0.05) -> tuple[float, float, float]:
    """Hold `key` for about `seconds`, with autorepeat as a real keyboard sends it. Returns the
    time it was held as the page handled it, and the least and most that Playwright's calls allow."""
    page.evaluate(KEY_TIMES)
    t0 = time.monotonic()
    page.keyboard.down(key)
    t0b = time.monotonic()  # the page handled the press by now (Playwright waits for that)
    while time.monotonic() - t0b < seconds:
        time.sleep(repeat_every)
        page.keyboard.down(key)  # Playwright sends these with repeat=true
    t1 = time.monotonic()
    page.keyboard.up(key)
    t1b = time.monotonic()
    times = page.evaluate("() => window.__keyTimes")
    (down,) = [t for kind, k, t in times if kind == "keydown" and k.lower() == key.lower()]
    (up,) = [t for kind, k, t in times if kind == "keyup" and k.lower() == key.lower()]
    return (up - down) / 1000.0, t1 - t0b, t1b - t0


def test_holding_w_moves_the_ee_plus_x_at_speed_for_the_time_held(page, server):
    before = settled(server, "a still arm")
    held_s, least, most = hold(page, "w", 2.0)
    print(f"held {held_s:.3f} s in the page; Playwright's calls allow {least:.3f}..{most:.3f} s")
    assert least - 0.01 <= held_s <= most + 0.01
    after = settled(server, "the hold to end")
    arrived = server.wait_for(lambda s: np.linalg.norm(np.array(s["ee_pos"][0]) - target(s)) < 0.01,
                              what="the EE to arrive")
    moved = target(after) - target(before)
    ee_moved = np.array(arrived["ee_pos"][0]) - np.array(before["ee_pos"][0])
    expected = POS_SPEED * held_s
    assert abs(moved[0] - expected) < 0.2 * expected, f"target moved {moved} in {held_s:.2f} s"
    assert abs(ee_moved[0] - expected) < 0.2 * expected, f"EE moved {ee_moved} in {held_s:.2f} s"
    assert np.all(np.abs(moved[1:]) < 0.005) and np.all(np.abs(ee_moved[1:]) < 0.015)
    assert after["page_keyboard"]["driving"].startswith("browser ")
    assert after["input_dropped"] == 0
    hold(page, "s", held_s)  # back where it was
    settled(server, "the way back")


def test_key_repeat_is_ignored(page, server):
    before = server.status()
    accepted = before["input"]["accepted"]
    page.keyboard.down("Space")
    for _ in range(6):
        page.keyboard.down("Space")  # autorepeat: not another toggle
    page.keyboard.up("Space")
    server.wait_for(lambda s: s["gripper_open"] != before["gripper_open"] and s["input"]["accepted"] >= accepted + 2,
                    what="the gripper to toggle and the release to arrive")
    time.sleep(1.0)  # time for a second toggle, were there one
    after = server.status()
    assert after["gripper_open"] == [not before["gripper_open"][0]]  # toggled exactly once
    assert after["input"]["accepted"] == accepted + 2  # one down, one up
    page.keyboard.press("Space")
    server.wait_for(lambda s: s["gripper_open"] == before["gripper_open"], what="the gripper back")


def test_losing_focus_releases_every_key(page, server):
    before = settled(server, "a still arm")
    page.keyboard.down("r")  # up...
    page.keyboard.down("a")  # ...and left, held
    server.wait_for(lambda s: sorted(sum(s["page_keyboard"]["held"].values(), [])) == ["a", "r"], what="two keys held")
    cdp = page.context.new_cdp_session(page)
    other = page.context.new_page()
    try:
        # Headless Chromium keeps every page focused unless told not to; then the tab in front has the focus.
        cdp.send("Emulation.setFocusEmulationEnabled", {"enabled": False})
        other.bring_to_front()
        assert page.evaluate("document.hasFocus()") is False  # the page got a real blur
        status = server.wait_for(lambda s: not s["page_keyboard"]["held"], timeout_s=30, what="the keys let go")
        assert status["page_keyboard"]["last_release"] == "blur"
        stopped = settled(server, "the arm to stop")
        assert target(stopped)[2] > target(before)[2] + 0.002  # it moved while held...
        time.sleep(1.0)  # ...and stays stopped with the keys still down
        assert np.allclose(target(server.status()), target(stopped), atol=1e-6)
    finally:
        page.keyboard.up("r")
        page.keyboard.up("a")
        other.close()
        cdp.send("Emulation.setFocusEmulationEnabled", {"enabled": True})
        cdp.detach()
        page.bring_to_front()
    assert page.evaluate("window.__teleopInput.held()") == []
    hold(page, "f", 0.2)
    hold(page, "d", 0.2)
    settled(server, "the arm back")


async def _hold_then(url: str, then: str) -> None:
    async with connect(url) as ws:
        await ws.send(json.dumps({"type": "hello", "client": None, "agent": "test"}))
        await ws.send(json.dumps({"type": "key", "key": "a", "down": True}))
        await asyncio.sleep(0.5)
        if then == "stall":
            time.sleep(QUIET_S + 1.5)  # this loop answers no ping meanwhile, as over a stalled network
            await asyncio.sleep(0.2)


@pytest.mark.e2e  # starts this module's `teleop serve` server, and waits out a stalled connection
@pytest.mark.parametrize("then, reason", [("close", "closed"), ("stall", "quiet")])
def test_a_connection_that_closes_or_stalls_lets_go_of_its_keys(server, then, reason):
    before = settled(server, "a still arm")
    headless.run_async(_hold_then(server.url.replace("http://", "ws://") + PATH, then))
    status = server.wait_for(lambda s: not s["page_keyboard"]["held"], timeout_s=30, what="the keys let go")
    assert status["page_keyboard"]["last_release"] == reason
    stopped = settled(server, "the arm to stop")
    left = target(stopped)[1] - target(before)[1]
    bound = POS_SPEED * (0.5 + (QUIET_S + 1.0 if then == "stall" else 0.0) + 0.5)
    assert 0.2 * POS_SPEED * 0.5 < left < bound  # moved while held, then stopped


MALFORMED = ['{"type": "key", "key": "w", "down": 1}', "{oops", '{"type": "key", "key": "w", "down": true, "x": 0}',
             '{"type": "hello", "client": NaN, "agent": ""}', '{"type": "teleport", "to": [9, 9, 9]}',
             '{"type": "key", "key": "q", "down": true}', '{"type": "release_all", "why": 1e999}', "[]", "null",
             '{"type": "hello", "client": 1.5, "agent": ""}', "x" * 2000]


async def _send_malformed(url: str) -> None:
    async with connect(url) as ws:
        for raw in MALFORMED:
            await ws.send(raw)
        await ws.send(b"\x00\x01binary")
        await asyncio.sleep(0.3)


def test_malformed_messages_are_dropped_without_disturbing_a_recording(page, server, record_dir):
    dropped = server.status()["input_dropped"]
    saved = server.status()["episodes_saved"]
    page.keyboard.press("b")  # start recording, from the page's keys
    server.wait_for(lambda s: s["recording"] and s["episode_steps"] > 10, what="recording")
    held_s, _, _ = hold(page, "w", 1.0)
    headless.run_async(_send_malformed(server.url.replace("http://", "ws://") + PATH))
    page.evaluate("raw => raw.forEach(m => window.__teleopInput.sendRaw(m))", MALFORMED[:3])
    during = server.wait_for(lambda s: s["input_dropped"] >= dropped + len(MALFORMED) + 4, what="the drops counted")
    steps = during["episode_steps"]
    later = server.wait_for(lambda s: s["episode_steps"] > steps + 30, what="the recording to go on")
    assert later["input_dropped"] == dropped + len(MALFORMED) + 4  # each one dropped and counted, once
    assert later["recording"] and later["error"] is None and later["recording_error"] is None
    assert later["input"]["last_drop"]
    assert page.evaluate("window.__teleopInput.connected()")  # the page's channel carries on
    page.keyboard.press("Enter")  # save
    status = server.wait_for(lambda s: s["episodes_saved"] == saved + 1 and not s["recording"], what="the save")
    newest = Path(status["saved_files"][-1])
    assert newest.parent == record_dir
    server.wait_for(lambda s: s["verified"].get(str(newest)) is True, timeout_s=90, what="exact replay")
    hold(page, "s", held_s)
    settled(server, "the arm back")


def test_every_browser_drives_and_the_panel_names_the_one_driving(page, server, browser):
    second = open_keyboard_page(browser, server)
    try:
        server.wait_for(lambda s: s["page_keyboard"]["browsers"] >= 2, what="two browsers on the channel")
        before = settled(server, "a still arm")
        second.keyboard.down("r")
        status = server.wait_for(lambda s: s["page_keyboard"]["held"], what="the second page's key")
        driver = status["page_keyboard"]["driving"]
        (holder,) = status["page_keyboard"]["held"]
        assert driver == holder and driver.startswith("browser ")
        for shown in (page, second):  # the panel says so, in every browser
            shown.get_by_text(f"driving: {driver}", exact=False).first.wait_for(state="attached", timeout=60_000)
        server.wait_for(lambda s: target(s)[2] > target(before)[2] + 0.01, timeout_s=60, what="the held r to raise the arm")
        second.keyboard.up("r")
        assert target(settled(server, "the rise"))[2] > target(before)[2] + 0.01
        hold(page, "f", 0.3)  # the first browser drives too, and the panel follows
        status = settled(server, "the first page's key")
        assert status["page_keyboard"]["driving"] != driver
        now = status["page_keyboard"]["driving"]
        page.get_by_text(f"driving: {now}", exact=False).first.wait_for(state="attached", timeout=60_000)
    finally:
        second.context.close()
    server.wait_for(lambda s: s["page_keyboard"]["browsers"] == 1, what="the second page gone")


VIEW_SIZE = """(() => {  // the 3D view's canvas (the one drawing the most pixels; an overlay has none): drawn and CSS pixels
  const c = [...document.querySelectorAll("canvas")].sort((a, b) => b.width * b.height - a.width * a.height)[0];
  return [c.width, c.height, c.clientWidth, c.clientHeight];
})()"""
GPU_RENDERER = """
(() => {  // this browser says its WebGL runs on a GPU, whatever draws it
  for (const Context of [WebGLRenderingContext, WebGL2RenderingContext]) {
    const original = Context.prototype.getParameter;
    Context.prototype.getParameter = function (name) {
      if (name === 0x9246 || name === this.RENDERER) return "ANGLE (NVIDIA, NVIDIA GeForce RTX 4090 Direct3D11)";
      return original.call(this, name);
    };
  }
})();
"""


def test_a_browser_drawing_in_software_gets_the_cheap_view_and_others_keep_viser_s(page, server, browser):
    """Headless Chromium draws WebGL with SwiftShader: the page draws at half resolution and gets no shadows or
    environment map (teleop/web/shared/view_quality.py); a page that reports a GPU renderer keeps viser's look."""
    # this module's one page left (an earlier test's second page may still be closing), counted as software
    server.wait_for(lambda s: s["clients"] == 1 and s["software_views"] == 1, what="the page to report software WebGL")
    page.get_by_text("1 drawing without a GPU", exact=False).first.wait_for(state="attached", timeout=60_000)
    # viser was asked, before it started, for half the display's resolution (its fixedDpr setting)...
    assert page.evaluate("new URLSearchParams(location.search).get('fixedDpr')") == "0.5"
    size = page.evaluate(VIEW_SIZE)
    assert size[0] == round(size[2] * 0.5) and size[1] == round(size[3] * 0.5) and size[2] > 100  # ...and draws at it

    context = browser.new_context(viewport={"width": PAGE_SIZE[0], "height": PAGE_SIZE[1]})
    context.add_init_script(GPU_RENDERER)
    gpu = context.new_page()
    try:
        gpu.goto(server.url, timeout=60000)
        gpu.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60000)
        server.wait_for(lambda s: s["clients"] == 2 and s["input"]["accepted"] > 0, what="a second browser")
        time.sleep(1.0)  # its view message has come by now
        assert server.status()["software_views"] == 1
        assert gpu.evaluate("new URLSearchParams(location.search).get('fixedDpr')") is None  # full resolution
        size = gpu.evaluate(VIEW_SIZE)
        assert size[0] == size[2] and size[2] > 100
    finally:
        context.close()
    server.wait_for(lambda s: s["clients"] == 1, what="the second page gone")
