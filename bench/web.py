"""Browser session speed: what a scene update costs, what a browser receives, whether the loop keeps real time.

Figures (`measure`):
  web_update_ms          server-side cost of one scene update in the thread that draws (the snapshot's
                         body poses into mjviser's handles, markers, gizmo, the frame for the pages
                         built and handed to viser's loop), median, with the arm moving so that every
                         update is sent and one page (a raw websocket client) connected (lift, Panda)
  web_updates_per_s      scene updates per second a headless Chromium received (counted inside
                         viser's worker: decoded batches that move bodies) from `teleop serve
                         --control-hz 60` while the arm moves: the drawer's 60 Hz cap is the limit;
                         web_updates_sent_per_s is what the server sent in the same window
  web_updates_per_s_at_30hz  the same from the default session (30 Hz: one update per tick in
                         which something moved, so 30 is its ceiling), recording
  serve_realtime_factor  simulated / wall time of `teleop serve` (default 30 Hz) while recording an
                         episode and streaming to one browser; 1.0 is real time
  serve_headroom_x       control period / median compute time of one tick in that same run: how
                         many times faster than real time the loop could run
  browser_key_latency_ms from a key pressed in headless Chromium (Playwright's keyboard.down) to the
                         control tick that applies it (the page's input channel, the keyboard device),
                         median; goal <= one control tick (33 ms at 30 Hz) + 10 ms
  browser_key_to_drawn_ms  from the same press to the page receiving the first scene update that
                         moves the arm (viser's worker handing it to the page), median
  browser_key_latency_ms_3d_hidden  browser_key_latency_ms with the page's 3D view hidden: headless
                         Chromium draws WebGL in software on the page's main thread, where keys wait
                         for the frame in progress; this is the input path without that. (With the
                         view shown the page gets teleop's software-WebGL view, as any browser without
                         a GPU does: teleop/web/shared/view_quality.py)

The browser figures need a system Chromium and Playwright (skipped, with a note, otherwise).
Moving the arm without a person: the session also runs a script device that sweeps the target.
"""

from __future__ import annotations

import json
import signal
import socket
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np


def _sweep_script(path: Path, seconds: float) -> Path:
    steps = []
    for i in range(int(seconds // 2) + 1):
        sign = 1 if i % 2 == 0 else -1
        steps.append({"duration": 1.0, "move": [0.08 * sign, 0.0, 0.0]})
        steps.append({"duration": 1.0, "move": [0.0, 0.08 * sign, -0.04 * sign]})
    path.write_text(json.dumps({"steps": steps}))
    return path


def update_cost_ms(updates: int) -> float:
    """Median server-side cost of one scene update, in process, arm moving every tick."""
    import viser

    from websockets.sync.client import connect

    from devices.command import Command
    from teleop.control.session import Session
    from teleop.web.session_page.drawing import SceneDrawer
    from teleop.web.session_page.sim_thread import SimThread
    from teleop.web.viser_internals import install
    from teleop.web.viser_internals.serving_hooks import WEBSOCKET_PROTOCOL

    class Sweep:
        name = kind = "sweep"

        def __init__(self) -> None:
            self.t = 0.0

        def poll(self, view, dt):
            self.t += dt
            return [Command(translation=np.array([0.002 * np.cos(self.t * 3), 0.002 * np.sin(self.t * 3), 0.0]))]

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    install()  # viser's patches, as an app's start installs them (teleop.web.viser_internals.guarded_start.start_guarded)
    server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    page = connect(f"ws://127.0.0.1:{port}", subprotocols=[WEBSOCKET_PROTOCOL], max_size=None)

    def take_all() -> None:  # a page that takes every frame: the updates are built and sent, as to a browser
        try:
            while True:
                page.recv()
        except Exception:  # noqa: BLE001 - closed at the end
            pass

    threading.Thread(target=take_all, daemon=True).start()
    try:
        sim = SimThread(Session(), [Sweep()], log=lambda m: None)
        drawer = SceneDrawer(server, sim)
        costs = []
        for _ in range(updates + 20):
            cost = drawer.draw(sim.step_once())
            if cost > 0:
                costs.append(cost)
        return float(np.median(costs[20:])) * 1000.0
    finally:
        page.close()
        server.stop()


def _rate(first: dict, last: dict) -> float:
    wall = last["wall_time"] - first["wall_time"]
    return (last["tick"] - first["tick"]) / last["control_hz"] / wall if wall > 0 else 0.0


def _updates_per_s(page, server, seconds: float) -> tuple[float, float, dict, dict]:
    """Scene updates/s the page received and the server sent over `seconds`; with the statuses around it."""
    from tests import browser as headless

    got0, first = headless.scene_updates_received(page), server.status()
    time.sleep(seconds)
    got1, last = headless.scene_updates_received(page), server.status()
    wall = last["wall_time"] - first["wall_time"]
    return (got1 - got0) / wall, (last["web_updates"] - first["web_updates"]) / wall, first, last


def browser_figures(quick: bool) -> dict[str, float]:
    from playwright.sync_api import sync_playwright

    from tests import browser as headless

    window = 4.0 if quick else 10.0
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory(prefix="teleop-bench-web-") as tmp:
        work = Path(tmp)
        script = _sweep_script(work / "sweep.json", 2 * window + 60)
        with sync_playwright() as p:
            browser = headless.launch(p, msaa=True)  # as a user's browser draws
            try:
                # The default session (30 Hz) recording an episode and streaming to one browser.
                server = headless.ServeProcess(["--device", f"gizmo,script:{script}", "--record", str(work / "eps")], work)
                try:
                    page = headless.open_page(browser, server.url, count_frames=True)
                    headless.click_button(page, "Record")
                    server.wait_for(lambda s: s["recording"], what="recording")
                    time.sleep(1.0)
                    received, sent, first, last = _updates_per_s(page, server, window)
                    assert last["recording"] and last["clients"] >= 1, "the run was not recording and streaming"
                    out["web_updates_per_s_at_30hz"] = round(received, 1)
                    out["web_updates_sent_per_s_at_30hz"] = round(sent, 1)
                    out["serve_realtime_factor"] = round(_rate(first, last), 4)
                    out["serve_headroom_x"] = round(float(last["headroom_x"]), 1)
                    out["serve_tick_ms"] = round(float(last["tick_ms"]), 3)
                    page.close()
                finally:
                    server.stop(signal.SIGINT)
                # What a browser takes when the state changes faster: 60 Hz control, drawer-capped.
                server = headless.ServeProcess(["--device", f"gizmo,script:{script}", "--control-hz", "60"], work)
                try:
                    page = headless.open_page(browser, server.url, count_frames=True)
                    server.wait_for(lambda s: s["clients"] >= 1, what="the page")
                    time.sleep(2.0)
                    received, sent, _, _ = _updates_per_s(page, server, window)
                    out["web_updates_per_s"] = round(received, 1)
                    out["web_updates_sent_per_s"] = round(sent, 1)
                    page.close()
                finally:
                    server.stop()
            finally:
                browser.close()
    return out


# In viser's worker: the wall times (Date.now(), ms) of the scene updates that move a body after
# `self.__since`; tests/browser.py's COUNT_FRAMES counts the same batches.
FIRST_UPDATE = r"""
(() => {
  const Original = window.Worker;
  window.Worker = function (scriptUrl, options) {
    const patch = `(() => { self.__since = Infinity; self.__times = []; self.__last = 0;
      const post = self.postMessage.bind(self);
      self.postMessage = function (data, ...rest) {
        if (data && data.type === 'message_batch' && Array.isArray(data.messages) && data.messages.some((m) =>
            m && m.type === 'SceneNodeUpdateMessage' && typeof m.name === 'string' && m.name.startsWith('/bodies/'))) {
          const now = Date.now(); self.__last = now;
          if (now >= self.__since && self.__times.length < 200) self.__times.push(now);
        }
        return post(data, ...rest);
      };
    })();`;
    const load = options && options.type === 'module'
      ? `\nimport ${JSON.stringify(String(scriptUrl))};` : `\nimportScripts(${JSON.stringify(String(scriptUrl))});`;
    return new Original(URL.createObjectURL(new Blob([patch + load], {type: 'text/javascript'})), options);
  };
  window.Worker.prototype = Original.prototype;
})();
"""


def _worker_value(page, expression: str):
    for worker in page.workers:
        try:
            value = worker.evaluate(expression)
        except Exception:  # noqa: BLE001 - a worker that went away
            continue
        if value is not None:
            return value
    return None


HIDE_3D = r"""
document.addEventListener("DOMContentLoaded", () => {
  const style = document.createElement("style");
  style.textContent = "canvas { display: none !important; }";
  document.head.appendChild(style);
});
"""


def key_latency(presses: int, hide_3d: bool = False) -> dict[str, float]:
    """A key held in headless Chromium's page: to the control tick that applies it, and to the page
    receiving the moved arm (medians, ms). In process, so the tick's time is read where it happens.

    hide_3d: the page's canvases hidden. Headless Chromium draws WebGL in software (SwiftShader) on
    the page's main thread, and a key is handled only between two frames; hidden, the figure is the
    input path alone (the page, its websocket, the channel, the keyboard device, the tick).
    """
    from playwright.sync_api import sync_playwright

    from teleop.control.session import Session
    from teleop.web.session_page.app import WebApp
    from teleop.web.session_page.serve_options import ServeOptions
    from tests import browser as headless

    session = Session("lift", "panda", seed=0, control_hz=30)
    app = WebApp(session, [], [], ServeOptions(port=headless.free_port(), page_keyboard=True), camera=False, log=lambda line: None)
    keyboard = app.page_keys.keyboard
    applied: list[float] = []
    poll = keyboard.poll

    def timed_poll(view, dt):
        commands = poll(view, dt)
        if any(c.translation.any() for c in commands):
            applied.append(time.monotonic())
        return commands

    keyboard.poll = timed_poll  # the device the control loop polls: stamp the tick that first moves
    to_tick: list[float] = []
    to_drawn: list[float] = []
    app.start()
    try:
        with sync_playwright() as p:
            browser = headless.launch(p, msaa=True)  # as a user's browser draws
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.add_init_script(FIRST_UPDATE)
                if hide_3d:
                    page.add_init_script(HIDE_3D)
                page.goto(app.url, timeout=60000)
                page.wait_for_function("window.__teleopInput && window.__teleopInput.connected()", timeout=60000)
                time.sleep(2.0)
                for i in range(presses):
                    key = "w" if i % 2 == 0 else "s"  # back and forth: the arm stays in its workspace
                    deadline = time.monotonic() + 10
                    while time.monotonic() < deadline:  # at rest: no scene update for 0.5 s
                        last = _worker_value(page, "self.__last") or 0
                        if time.time() * 1000 - last > 500:
                            break
                        time.sleep(0.1)
                    since = time.time() * 1000
                    _worker_value(page, f"(self.__since = {since}, self.__times = [], 1)")
                    count = len(applied)
                    t0 = time.monotonic()
                    page.keyboard.down(key)
                    while len(applied) == count and time.monotonic() - t0 < 5:
                        time.sleep(0.0005)
                    if len(applied) > count:
                        to_tick.append((applied[count] - t0) * 1000)
                        # the first update the page got from that tick on (wall clock, as the worker's)
                        tick_wall = (time.time() - (time.monotonic() - applied[count])) * 1000
                        while time.monotonic() - t0 < 5:
                            first = next((t for t in (_worker_value(page, "self.__times") or []) if t >= tick_wall - 1), None)
                            if first:
                                to_drawn.append(first - since)
                                break
                            time.sleep(0.005)
                    time.sleep(0.3)
                    page.keyboard.up(key)
            finally:
                browser.close()
    finally:
        app.close()
    if hide_3d:
        return {"browser_key_latency_ms_3d_hidden": round(float(np.median(to_tick)), 1) if to_tick else None}
    return {
        "browser_key_latency_ms": round(float(np.median(to_tick)), 1) if to_tick else None,
        "browser_key_to_drawn_ms": round(float(np.median(to_drawn)), 1) if to_drawn else None,
        "browser_key_presses": len(to_tick),
    }


def measure(quick: bool) -> dict[str, float]:
    figures = {"web_update_ms": round(update_cost_ms(100 if quick else 400), 3)}
    try:
        figures.update(browser_figures(quick))
        figures.update(key_latency(6 if quick else 20))
        figures.update(key_latency(6 if quick else 20, hide_3d=True))
    except (ImportError, FileNotFoundError) as exc:
        print(f"bench web: browser figures skipped ({exc})", file=sys.stderr)
    return figures


if __name__ == "__main__":
    print(json.dumps(measure("--quick" in sys.argv)))
