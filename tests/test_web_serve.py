"""`teleop serve` in a real headless Chromium: the page, the gizmo, the buttons, the recording.

One server (a `python -m teleop serve` subprocess recording into a temp dir)
and one browser serve the whole module; the server's state is read from its
status file. Needs Debian's chromium (or TELEOP_CHROMIUM) and Playwright's
Python package; nothing is downloaded.
"""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest


from tests import browser as headless  # noqa: E402
from tests.support import run_cli, wait_until  # noqa: E402


REPO = Path(__file__).resolve().parents[1]
PAGE_SIZE = (1100, 720)  # software WebGL: fewer pixels, faster frames


@pytest.fixture(scope="module")
def record_dir(tmp_path_factory) -> Path:
    return tmp_path_factory.mktemp("episodes")


@pytest.fixture(scope="module")
def server(record_dir, tmp_path_factory):
    proc = headless.ServeProcess(["--record", str(record_dir), "--device", "gizmo"], tmp_path_factory.mktemp("serve"))
    yield proc
    proc.stop()


@pytest.fixture(scope="module")
def page(server, browser):
    page = headless.open_page(browser, server.url, count_frames=True, size=PAGE_SIZE)
    server.wait_for(lambda s: s["clients"] >= 1, what="the page to connect")
    time.sleep(2.0)  # first meshes drawn
    headless.dismiss_toasts(page)
    yield page
    page.close()


def episode_files(directory: Path) -> list[Path]:
    return sorted(p for p in directory.iterdir() if p.suffix in (".mcap", ".hdf5"))


def drag_x(page, server, pixels: float = 80.0) -> tuple[np.ndarray, dict]:
    """Drag the gizmo along its x arrow; returns the target before and the status once it moved."""
    target = np.array(server.status()["target_pos"][0])
    after = headless.drag_gizmo_until(page, server.status, lambda s: np.linalg.norm(np.array(s["target_pos"][0]) - target) > 0.03,
                                      pixels=pixels)
    return target, after


def canvas_pixels(page, path: Path) -> tuple[np.ndarray, dict, np.ndarray]:
    """Screenshot to `path`; returns (canvas crop, canvas box, whole image) as float RGB."""
    from PIL import Image

    page.screenshot(path=str(path))
    box = headless.canvas_box(page)
    image = np.asarray(Image.open(path).convert("RGB")).astype(float)
    crop = image[int(box["y"]):int(box["y"] + box["height"]), int(box["x"]):int(box["x"] + box["width"])]
    return crop, box, image


def test_page_shows_the_robot(page, tmp_path):
    from teleop.web.shared.camera_markers import CAMERA_FOV, CAMERA_LOOK_AT, CAMERA_POSITION

    shot = tmp_path / "page.png"
    deadline = time.monotonic() + 40  # software WebGL: the meshes take a while to appear
    while True:
        canvas, box, image = canvas_pixels(page, shot)
        colors = len(np.unique(canvas.reshape(-1, 3).astype(np.uint8), axis=0))
        if (canvas.std() > 20 and colors > 500) or time.monotonic() > deadline:
            break
        time.sleep(1.0)
    assert canvas.std() > 20 and colors > 500, f"canvas looks blank ({colors} colours, std {canvas.std():.1f}): {shot}"
    # The robot's links are light grey: there must be such pixels where its upper arm is drawn.
    x, y = headless.project((0.0, 0.0, 0.55), box, CAMERA_POSITION, CAMERA_LOOK_AT, CAMERA_FOV)
    patch = image[int(y) - 15:int(y) + 15, int(x) - 15:int(x) + 15]
    assert (patch.min(axis=2) > 170).mean() > 0.3, f"no robot-coloured pixels where the arm should be: {shot}"
    # and the table (tan) below the arm
    tx, ty = headless.project((0.45, 0.25, 0.0), box, CAMERA_POSITION, CAMERA_LOOK_AT, CAMERA_FOV)
    r, g, b = image[int(ty), int(tx)]
    assert r > b + 20, f"no table where it should be: {shot}"


def test_drag_gizmo_moves_the_arm(page, server):
    target, after = drag_x(page, server)
    assert after["target_pos"][0][0] > target[0] + 0.03  # dragged along +x
    moved = server.wait_for(lambda s: abs(s["ee_pos"][0][0] - s["target_pos"][0][0]) < 0.01,
                            what="the end effector to follow the target")
    assert moved["ee_pos"][0][0] > target[0] + 0.03
    assert moved["latency_ms"] is not None


def test_record_drag_save_replays_exactly(page, server, record_dir):
    saved_before = server.status()["episodes_saved"]
    files_before = set(episode_files(record_dir))
    headless.click_button(page, "Record")
    server.wait_for(lambda s: s["recording"], what="recording to start")
    page.get_by_role("button", name="Stop", exact=True).wait_for(timeout=30_000)
    drag_x(page, server, pixels=-60)
    server.wait_for(lambda s: s["episode_steps"] > 20, what="some recorded steps")
    headless.click_button(page, "Save")
    status = server.wait_for(lambda s: s["episodes_saved"] == saved_before + 1 and not s["recording"], what="the save")
    new = sorted(set(episode_files(record_dir)) - files_before)
    assert len(new) == 1, new
    result = run_cli("replay", str(new[0]), "--verify", timeout=120)
    assert result.returncode == 0, result.stdout + result.stderr
    checked = server.wait_for(lambda s: s["verified"].get(str(new[0])) is not None, what="the server's replay check")
    assert checked["verified"][str(new[0])] is True
    assert status["episodes_saved"] == saved_before + 1
    page.get_by_role("button", name="Record", exact=True).wait_for(timeout=30_000)


def test_save_moves_to_the_next_seed_with_the_arm_home(page, server, record_dir):
    """Issue 49, item 1: the episode starts from its seed's initial state, Save moves to the next seed (the
    cube placed anew, the arm home), the panel says so, and the file records the seed it started from."""
    import teleop
    from replay.episode import load_episode

    drag_x(page, server)  # the arm away from home before recording
    seed = server.status()["seed"]
    headless.click_button(page, "Record")
    started = server.wait_for(lambda s: s["recording"], what="recording to start")
    home = teleop.Session("lift", "panda", seed=seed).controller.target_pose()[0]
    assert started["seed"] == seed and np.allclose(started["target_pos"][0], home, atol=1e-6)  # Record put it home
    drag_x(page, server, pixels=-60)
    server.wait_for(lambda s: s["episode_steps"] > 20, what="some recorded steps")
    saved = server.status()["episodes_saved"]
    headless.click_button(page, "Save")
    after = server.wait_for(lambda s: s["episodes_saved"] == saved + 1 and not s["recording"], what="the save")
    assert after["seed"] == seed + 1 and after["fresh_episodes"] is True
    nxt = teleop.Session("lift", "panda", seed=seed + 1).controller
    assert np.allclose(after["target_pos"][0], nxt.target_pose()[0], atol=1e-6)  # the arm's target home
    assert np.allclose(after["objects"]["cube"][:2], nxt.data.qpos[9:11], atol=2e-3)  # the cube where seed+1 puts it
    page.get_by_text(f"Next episode: seed {seed + 1}, from its initial state").first.wait_for(timeout=60_000)
    assert load_episode(Path(after["saved_files"][-1])).meta.seed == seed


def test_discard_leaves_no_episode(page, server, record_dir):
    files_before = set(episode_files(record_dir))
    discarded = server.status()["episodes_discarded"]
    headless.click_button(page, "Record")
    server.wait_for(lambda s: s["recording"] and s["episode_steps"] > 10, what="recording")
    headless.click_button(page, "Discard")
    server.wait_for(lambda s: s["episodes_discarded"] == discarded + 1 and not s["recording"], what="the discard")
    time.sleep(0.3)
    assert set(episode_files(record_dir)) == files_before


def test_gripper_buttons(page, server):
    headless.click_button(page, "Close")
    server.wait_for(lambda s: s["gripper_open"] == [False], what="the gripper to close")
    headless.click_button(page, "Open")
    server.wait_for(lambda s: s["gripper_open"] == [True], what="the gripper to open")


def test_reset_changes_object_placement(page, server):
    before = server.status()
    headless.click_button(page, "Reset")
    after = server.wait_for(lambda s: s["seed"] == before["seed"] + 1, what="the reset")
    cube_before, cube_after = np.array(before["objects"]["cube"]), np.array(after["objects"]["cube"])
    assert np.linalg.norm(cube_after[:2] - cube_before[:2]) > 0.01
    # the gizmo follows the reset target (the arm is home again)
    server.wait_for(lambda s: np.linalg.norm(np.array(s["ee_pos"][0]) - np.array(s["target_pos"][0])) < 0.01,
                    what="the arm to settle at home")


def test_camera_picture_or_a_clear_note(page, server):  # pictures are drawn while a page watches
    status = server.wait_for(lambda s: s["camera_frames"] > 0 or s["camera_problem"], what="a camera picture")
    assert status["camera_frames"] > 0 or "MUJOCO_GL" in status["camera_problem"]


def test_two_pages_see_the_same_session(page, server, browser):
    second = headless.open_page(browser, server.url, count_frames=True, size=PAGE_SIZE)
    try:
        server.wait_for(lambda s: s["clients"] >= 2, what="two browsers")
        time.sleep(1.0)
        headless.dismiss_toasts(second)
        before = [headless.frames_received(p) for p in (page, second)]
        updates = server.status()["web_updates"]

        def closed() -> bool:  # closed, and drawn (a loaded machine may draw the whole close in one or two updates)
            status = server.status(missing_ok=True)
            return status.get("gripper_open") == [False] and status.get("web_updates", 0) > updates

        def seen() -> str:
            status = server.status(missing_ok=True)
            keys = ("gripper_open", "web_updates", "clients", "tick", "loop_hz", "slips", "input_dropped", "notes")
            return f"web_updates before {updates}, now {({k: status.get(k) for k in keys})}; page messages {before} -> " \
                   f"{[headless.frames_received(p) for p in (page, second)]}"

        # the second page drives the same robot...
        headless.click_until(second, "Close", closed, what="the fingers to move", show=seen)

        def gained() -> list[int]:
            return [headless.frames_received(p) - b for p, b in zip((page, second), before)]

        # ...and both see it move (waited for: a loaded machine hands a page its messages late)
        assert wait_until(lambda: min(gained()) >= 5, 60), f"a page missed the motion: {gained()} messages"
        headless.click_until(page, "Open", lambda: server.status(missing_ok=True).get("gripper_open") == [True],
                             what="the first page's click")
        status = server.status()
        # the loop kept going with two pages attached (how close to real time it keeps: bench/web.py)
        assert status["loop_hz"] > 0 and 0 < status["realtime_factor"] < 1.15  # paced, never ahead of the clock
    finally:
        second.close()


def test_closing_the_page_mid_episode_keeps_recording(server, browser, record_dir):
    first = headless.open_page(browser, server.url, size=PAGE_SIZE)
    server.wait_for(lambda s: s["clients"] >= 1, what="the page")
    headless.dismiss_toasts(first)
    saved = server.status()["episodes_saved"]
    headless.click_button(first, "Record")
    server.wait_for(lambda s: s["recording"], what="recording")
    first.close()
    steps = server.status()["episode_steps"]
    later = server.wait_for(lambda s: s["episode_steps"] > steps + 30, what="steps to keep coming")
    assert later["recording"]
    other = headless.open_page(browser, server.url, size=PAGE_SIZE)
    try:
        headless.dismiss_toasts(other)
        other.get_by_role("button", name="Stop", exact=True).wait_for(timeout=60_000)
        headless.click_button(other, "Stop")  # Stop saves
        status = server.wait_for(lambda s: s["episodes_saved"] == saved + 1 and not s["recording"], what="the save")
        newest = Path(status["saved_files"][-1])
        assert newest.exists() and newest.parent == record_dir
        server.wait_for(lambda s: s["verified"].get(str(newest)) is True, timeout_s=60, what="exact replay")
    finally:
        other.close()


def _addresses() -> list[str]:
    out = ["127.0.0.2"]
    try:
        words = subprocess.run(["hostname", "-I"], capture_output=True, text=True, timeout=5).stdout.split()
        out += [w for w in words if ":" not in w and not w.startswith("127.")]
    except (OSError, subprocess.SubprocessError):
        pass
    return out


@pytest.mark.e2e  # this module's `teleop serve` server
def test_listens_on_loopback_only(server):
    with socket.create_connection(("127.0.0.1", server.port), timeout=3):
        pass
    for address in _addresses():
        with pytest.raises(OSError):
            with socket.create_connection((address, server.port), timeout=3):
                pass


@pytest.mark.e2e  # this module's `teleop serve` server
def test_realtime_with_browsers(server):
    status = server.status()
    assert status["error"] is None
    assert 0.9 < status["realtime_factor"] < 1.1
    assert status["headroom_x"] > 2
