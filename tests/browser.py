"""Driving the page from a headless Chromium (Playwright): shared by the tests and the bench.

Uses the system's Chromium (Debian: /usr/bin/chromium, or $TELEOP_CHROMIUM); nothing is
downloaded. The browser tests (`pytest -m browser`) open the served page in it and use it
as a person would: drag the gizmo, press keys, click the panel's buttons, feed gamepad,
phone and WebHID events through init scripts, and check what the page draws. Without
Chromium they fail (an error naming the install, never a skip): install it with
`apt-get install chromium` (Debian/Ubuntu; `./run.sh test` does that as root) or point
TELEOP_CHROMIUM at a Chromium or Chrome binary. Two things need care and live here:

- viser's client talks to the server from a Web Worker, which Playwright's
  websocket events do not see. `COUNT_FRAMES` wraps the page's Worker
  constructor so that the worker counts the WebSocket messages it receives
  (`self.__wsFrames`) and the decoded batches it hands to the page that move
  one robot body (`self.__sceneUpdates`: one per scene update, even when viser
  splits an update across two messages; panel-only batches excluded), read
  with worker.evaluate.
- To drag the gizmo we need where a world point lands on screen: `project`
  does the pinhole projection of viser's initial camera (position, look-at,
  vertical field of view, z up) onto the canvas' box.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import time
from pathlib import Path

import numpy as np

CHROMIUM_ARGS = (
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
)
# The tests' Chromium draws WebGL without multisampling (a user's browser keeps it, and so does the bench's, so
# that its figures are what a user gets). Without a GPU, SwiftShader draws every frame of the page, and 4x MSAA
# doubled its cost: an idle session page (viser's 1 s heartbeat frame, half resolution) took 0.28 CPU s a frame
# with it and 0.15 without, measured in headless Chromium at 1280x800 on the 2-core machine. A page's edges
# are jagged; nothing a test checks is in them.
NO_MSAA_ARGS = ("--webgl-msaa-sample-count=0",)

COUNT_FRAMES = r"""
(() => {
  const Original = window.Worker;
  window.Worker = function (scriptUrl, options) {
    const patch = `(() => { const W = self.WebSocket; self.__wsFrames = 0;
      class Counting extends W { constructor(...a) { super(...a);
        this.addEventListener('message', () => { self.__wsFrames += 1; }); } }
      self.WebSocket = Counting;
      self.__sceneUpdates = 0; self.__sceneNode = null; const post = self.postMessage.bind(self);
      const moves = (m) => m && m.type === 'SceneNodeUpdateMessage' && typeof m.name === 'string'
        && m.name.startsWith('/bodies/') && (self.__sceneNode === null || m.name === self.__sceneNode);
      self.postMessage = function (data, ...rest) {
        if (data && data.type === 'message_batch' && Array.isArray(data.messages)) {
          const hit = data.messages.find(moves);
          if (hit) { self.__sceneNode = hit.name; self.__sceneUpdates += 1; }
        }
        return post(data, ...rest);
      };
    })();`;
    const load = options && options.type === 'module'
      ? `\nimport ${JSON.stringify(String(scriptUrl))};`
      : `\nimportScripts(${JSON.stringify(String(scriptUrl))});`;
    const blob = new Blob([patch + load], { type: 'text/javascript' });
    return new Original(URL.createObjectURL(blob), options);
  };
  window.Worker.prototype = Original.prototype;
})();
"""


def chromium_path() -> str | None:
    """The system Chromium, or None (the browser tests then fail with the install line; the bench reports nothing)."""
    for candidate in (os.environ.get("TELEOP_CHROMIUM"), "/usr/bin/chromium", shutil.which("chromium"),
                      shutil.which("chromium-browser"), shutil.which("google-chrome")):
        if candidate and os.path.exists(candidate):
            return candidate
    return None


def launch(playwright, msaa: bool = False):
    """A headless system Chromium (raises FileNotFoundError when there is none); `msaa`: WebGL antialiased as
    in a user's browser (the bench), else without multisampling (the tests: NO_MSAA_ARGS)."""
    path = chromium_path()
    if path is None:
        raise FileNotFoundError("no Chromium found: the browser tests drive the page in headless Chromium; install it "
                                "(Debian: apt-get install chromium) or set TELEOP_CHROMIUM to its path")
    return playwright.chromium.launch(executable_path=path, args=[*CHROMIUM_ARGS, *(() if msaa else NO_MSAA_ARGS)])


def open_page(browser, url: str, count_frames: bool = False, size=(1280, 800), timeout_s: float = 60.0):
    """Open the viser page and wait until the scene canvas is there."""
    page = browser.new_page(viewport={"width": size[0], "height": size[1]})
    if count_frames:
        page.add_init_script(COUNT_FRAMES)
    page.goto(url, timeout=timeout_s * 1000)
    page.wait_for_selector("canvas", timeout=timeout_s * 1000)
    return page


def _worker_counter(page, name: str) -> int:
    """Sum a counter the init script keeps in each of the page's workers."""
    total = 0
    for worker in page.workers:
        try:
            total += int(worker.evaluate(f"self.{name} || 0"))
        except Exception:  # noqa: BLE001 - a worker that went away counts nothing
            pass
    return total


def frames_received(page) -> int:
    """WebSocket messages the page's viser worker received so far (needs count_frames=True)."""
    return _worker_counter(page, "__wsFrames")


def scene_updates_received(page) -> int:
    """Scene updates (message batches that move bodies) the page's viser worker handed to the page."""
    return _worker_counter(page, "__sceneUpdates")


def dismiss_toasts(page) -> None:
    """Close viser's notifications (headless Chromium gets a 'software WebGL' one)."""
    for button in page.locator(".mantine-Notification-closeButton").all():
        try:
            button.dispatch_event("click", timeout=2000)
        except Exception:  # noqa: BLE001 - already gone
            pass


def canvas_box(page) -> dict:
    """The 3D canvas' box on the page (the largest canvas: the panel has small ones)."""
    boxes = [c.bounding_box() for c in page.locator("canvas").all()]
    boxes = [b for b in boxes if b]
    return max(boxes, key=lambda b: b["width"] * b["height"])


def project(point, box: dict, position, look_at, fov_y: float, up=(0.0, 0.0, 1.0)) -> tuple[float, float]:
    """Page pixel where world `point` appears, for a camera at `position` looking at `look_at`."""
    position, look_at, up = (np.asarray(v, dtype=float) for v in (position, look_at, up))
    forward = look_at - position
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, forward)
    d = np.asarray(point, dtype=float) - position
    depth = float(d @ forward)
    half_h = np.tan(fov_y / 2.0)
    aspect = box["width"] / box["height"]
    ndc_x = float(d @ right) / (depth * half_h * aspect)
    ndc_y = float(d @ cam_up) / (depth * half_h)
    return box["x"] + (ndc_x + 1.0) / 2.0 * box["width"], box["y"] + (1.0 - ndc_y) / 2.0 * box["height"]


def click_button(page, label: str, timeout_s: float = 60.0) -> None:
    """Click the panel button whose text is exactly `label`.

    The click is dispatched to the button itself: with software WebGL a page
    may draw only a few frames a second, and a mouse click would first wait
    for the layout to be "stable" over two frames.
    """
    button = page.get_by_role("button", name=label, exact=True).first
    button.wait_for(state="visible", timeout=timeout_s * 1000)
    button.dispatch_event("click", timeout=timeout_s * 1000)


def click_until(page, label: str, done, timeout_s: float = 120.0, what: str = "the click's effect",
                again_s: float = 20.0, show=None) -> None:
    """Click the panel button `label` until `done()` is true; fails naming `what` (and `show()`) after `timeout_s`.

    For a button whose click may be repeated (Close, Open: a second click asks for what the first did). A click
    made while a loaded page was still catching up with its server (or reconnecting) can be lost; the page is
    then clicked again every `again_s` without the effect.
    """
    deadline = time.monotonic() + timeout_s
    while True:
        click_button(page, label, timeout_s=max(1.0, deadline - time.monotonic()))
        again = min(deadline, time.monotonic() + again_s)
        while time.monotonic() < again:
            if done():
                return
            time.sleep(0.1)
        if time.monotonic() >= deadline:
            seen = f"; {show()}" if show is not None else ""
            raise AssertionError(f"timed out after {timeout_s:.0f} s clicking {label!r}, waiting for {what}{seen}")


def pick(page, label: str, option: str, timeout_s: float = 60.0) -> None:
    """Choose `option` in the panel dropdown labelled `label` and wait until the page shows it chosen."""
    page.get_by_label(label, exact=True).dispatch_event("click", timeout=timeout_s * 1000)
    page.get_by_role("option", name=option, exact=True).dispatch_event("click", timeout=timeout_s * 1000)
    page.wait_for_function("([l, o]) => [...document.querySelectorAll('input')].some("
                           "i => i.value === o && i.id && document.querySelector(`label[for='${i.id}']`)"
                           "?.textContent.trim() === l)", arg=[label, option], timeout=timeout_s * 1000)


def hold_until(page, key: str, done, timeout_s: float = 120.0, what: str = "the held key's effect",
               press_again_s: float = 15.0) -> None:
    """Hold `key` in `page` until `done()` is true, then let go; fails naming `what` after `timeout_s`.

    The server times a hold from the press to the release as they reach it, so on a loaded machine a
    hold of a fixed time can arrive as a press and a release together and move nothing: hold until the
    effect shows instead. If the server let go meanwhile (a connection that stalled past its pings), a
    held key would do nothing more: every `press_again_s` without the effect the key is pressed anew.
    """
    deadline = time.monotonic() + timeout_s
    page.keyboard.down(key)
    pressed = time.monotonic()
    try:
        while not done():
            now = time.monotonic()
            if now >= deadline:
                raise AssertionError(f"timed out after {timeout_s:.0f} s holding {key!r}, waiting for {what}")
            if now - pressed > press_again_s:
                page.keyboard.up(key)
                page.keyboard.down(key)
                pressed = time.monotonic()
            time.sleep(0.05)
    finally:
        page.keyboard.up(key)


def run_async(coroutine):
    """Run a coroutine to the end on a thread of its own and return its result (or raise its error).

    Playwright's sync API keeps an asyncio loop running on the test's thread,
    where `asyncio.run` refuses to start, so a websocket client runs beside it.
    """
    import asyncio
    import threading

    out: dict = {}

    def main() -> None:
        try:
            out["result"] = asyncio.run(coroutine)
        except BaseException as exc:  # noqa: BLE001 - handed to the caller
            out["error"] = exc

    thread = threading.Thread(target=main, daemon=True)
    thread.start()
    thread.join()
    if "error" in out:
        raise out["error"]
    return out["result"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class ServeProcess:
    """`python -m teleop serve ...` in a subprocess, observed through its status file."""

    def __init__(self, args: list[str], workdir: Path, port: int | None = None, env: dict | None = None,
                 ready_timeout_s: float = 90.0) -> None:
        self.port = port or free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.status_file = Path(workdir) / f"serve-status-{self.port}.json"
        self.log_file = Path(workdir) / f"serve-{self.port}.log"
        from tests.support import popen_cli

        command = ["serve", "--port", str(self.port), "--status-file", str(self.status_file), *args]
        self._log = open(self.log_file, "w")
        self.status_file.unlink(missing_ok=True)  # a server before on this port (a restart) left its own
        self.proc = popen_cli(command, self._log, env=env, cwd=Path(__file__).resolve().parents[2])
        deadline = time.monotonic() + ready_timeout_s
        while time.monotonic() < deadline:
            if self.proc.poll() is not None:
                raise RuntimeError(f"teleop serve exited with {self.proc.returncode}: {self.log()[-2000:]}")
            status = self.status(missing_ok=True)
            if status and status.get("tick", 0) > 0 and status.get("pid") == self.proc.pid:
                return
            time.sleep(0.2)
        self.stop()
        raise TimeoutError(f"teleop serve did not start in {ready_timeout_s} s: {self.log()[-2000:]}")

    def status(self, missing_ok: bool = False) -> dict:
        try:
            return json.loads(self.status_file.read_text())
        except (FileNotFoundError, json.JSONDecodeError):
            if missing_ok:
                return {}
            raise

    def wait_for(self, predicate, timeout_s: float = 60.0, what: str = "condition") -> dict:
        """Poll the status until `predicate(status)` holds; returns that status (generous by default: the
        suite runs on parallel workers, and a loaded machine answers late, not wrongly)."""
        deadline = time.monotonic() + timeout_s
        status = {}
        while time.monotonic() < deadline:
            status = self.status(missing_ok=True)
            if status and predicate(status):
                return status
            time.sleep(0.1)
        raise TimeoutError(f"timed out waiting for {what}; last status: {json.dumps(status)[:1500]}")

    def log(self) -> str:
        if not self._log.closed:
            self._log.flush()
        return self.log_file.read_text()

    def stop(self, sig: int = signal.SIGINT, timeout_s: float = 30.0) -> int:
        """Stop as Ctrl-C does; returns the exit code."""
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        if not self._log.closed:
            self._log.close()
        return self.proc.returncode


def drag_gizmo_axis(page, target_pos, target_quat, axis: int = 0, pixels: float = 80.0, steps: int = 8,
                    step_s: float = 0.03) -> None:
    """Grab the gizmo's `axis` arrow (in the target's frame) and drag it `pixels` along its screen direction."""
    import mujoco

    from teleop.web.session_page.drawing import GIZMO_SCALE
    from teleop.web.shared.camera_markers import CAMERA_FOV, CAMERA_LOOK_AT, CAMERA_POSITION

    rot = np.empty(9)
    mujoco.mju_quat2Mat(rot, np.asarray(target_quat, dtype=float))
    direction = rot.reshape(3, 3)[:, axis]
    box = canvas_box(page)
    view = (box, CAMERA_POSITION, CAMERA_LOOK_AT, CAMERA_FOV)
    grab = np.array(project(np.asarray(target_pos) + 0.75 * GIZMO_SCALE * direction, *view))
    ahead = np.array(project(np.asarray(target_pos) + 1.0 * GIZMO_SCALE * direction, *view))
    along = (ahead - grab) / max(np.linalg.norm(ahead - grab), 1e-9)
    page.mouse.move(*grab)
    time.sleep(0.2)
    page.mouse.down()
    for i in range(1, steps + 1):
        page.mouse.move(*(grab + along * pixels * i / steps))
        time.sleep(step_s)
    page.mouse.up()


def drag_gizmo_until(page, status, moved, axis: int = 0, pixels: float = 80.0, timeout_s: float = 120.0,
                     what: str = "the gizmo drag to move the target") -> dict:
    """Drag the gizmo's `axis` arrow until `moved(status())` holds; returns that status.

    `status()` is the server's status (target_pos, target_quat of arm 0). On a loaded machine software WebGL
    may not have drawn the gizmo when the drag starts, and a drag that grabs nothing moves nothing: the arrow
    is dragged again (from where the target is now) until the target moves or `timeout_s` passes.
    """
    deadline = time.monotonic() + timeout_s
    now = status()
    while True:
        drag_gizmo_axis(page, now["target_pos"][0], now["target_quat"][0], axis=axis, pixels=pixels)
        retry = min(deadline, time.monotonic() + 15.0)
        while True:
            now = status()
            if moved(now):
                return now
            if time.monotonic() >= retry:
                break
            time.sleep(0.1)
        if time.monotonic() >= deadline:
            raise AssertionError(f"timed out after {timeout_s:.0f} s waiting for {what}; last status: {json.dumps(now)[:800]}")
