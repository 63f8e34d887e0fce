"""Subtasks in `teleop replay PATH --serve`: listed on the timeline, a boundary moved, removed, added, saved."""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from replay.subtasks.sidecar import Subtask
from replay.subtasks.edit import EditRefused, SubtaskEdits, even_split
from teleop.web.replay_subtasks import step_from_browser, timeline_html
from tests import browser as headless

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scenes" / "scripts" / "stack_pick.json"  # grasp the cube, place it on cube_base


def test_edits_keep_the_subtasks_contiguous():
    edits = SubtaskEdits([Subtask("cube", 0, 60), Subtask("cube_base", 60, 100)], 100)
    edits.move(0, 70)
    assert edits.boundaries == [70]
    for bad in (0, 100, 150, -3):
        with pytest.raises(EditRefused, match="between steps 0 and 100"):
            edits.move(0, bad)
    with pytest.raises(EditRefused, match="no boundary 2"):
        edits.move(1, 50)
    assert edits.add(85, "bin") == 1 and [s.object for s in edits.subtasks] == ["cube", "cube_base", "bin"]
    with pytest.raises(EditRefused, match="already a boundary"):
        edits.add(85, "cube")
    edits.remove(0)
    assert edits.subtasks == [Subtask("cube", 0, 85), Subtask("bin", 85, 100)]
    assert edits.set_object(90, "cube_base") == 1 and edits.subtasks[1].object == "cube_base"
    assert even_split(["a", "b", "c"], 10) == [Subtask("a", 0, 3), Subtask("b", 3, 7), Subtask("c", 7, 10)]
    assert even_split(["a", "b"], 1) == [Subtask("a", 0, 1)]


def test_values_from_the_browser_are_checked():
    assert step_from_browser(12, 100) == 12 and step_from_browser(12.0, 100) == 12
    for bad in (12.5, float("nan"), float("inf"), -1, 100, "12", None, True):
        assert step_from_browser(bad, 100) is None, bad
    bar = timeline_html([Subtask("<b>x</b>", 0, 5)], 5, 2, [])
    assert "<b>x</b>" not in bar and "&lt;b&gt;" in bar  # object names are escaped


@pytest.fixture(scope="module")
def episode(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("annotate")
    subprocess.run([sys.executable, "-m", "teleop", "run", "--scene", "stack", "--device", f"script:{SCRIPT}",
                    "--record", str(work / "eps"), "--json"], cwd=REPO, check=True, capture_output=True, timeout=120)
    (path,) = sorted((work / "eps").glob("*.mcap"))
    return path


def _inspect_subtasks(path: Path) -> list[dict] | None:
    out = subprocess.run([sys.executable, "-m", "teleop", "inspect", str(path), "--json"], cwd=REPO, check=True,
                         capture_output=True, text=True, timeout=60).stdout
    return json.loads(out)["subtasks"]


def test_subtasks_are_edited_and_saved_in_the_browser(episode, tmp_path):
    import playwright.sync_api as playwright_api  # the test extra installs it; Chromium comes from run.sh
    sidecar = episode.with_name(episode.name + ".subtasks.json")
    assert not sidecar.exists()
    port = headless.free_port()
    log_path = tmp_path / "replay.log"
    log = open(log_path, "w")
    proc = subprocess.Popen([sys.executable, "-m", "teleop", "replay", str(episode), "--serve", "--port", str(port)],
                            cwd=REPO, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and "open http" not in log_path.read_text():
            assert proc.poll() is None, log_path.read_text()
            time.sleep(0.2)
        with playwright_api.sync_playwright() as p:
            browser = headless.launch(p)
            page = headless.open_page(browser, f"http://127.0.0.1:{port}", size=(900, 700))

            def shows(pattern: str, timeout_s: float = 30.0) -> None:
                """Wait until some element's text matches the regex `pattern` (a loaded machine draws slowly)."""
                page.wait_for_function("(p) => [...document.querySelectorAll('*')]"
                                       ".some(e => new RegExp(p).test(e.textContent.trim()))",
                                       arg=pattern, timeout=timeout_s * 1000, polling=100)

            def go_to(step: int) -> None:
                box = page.locator("input.mantine-NumberInput-input:visible").first  # the Step slider's box
                box.fill(str(step))
                box.press("Enter")
                shows(rf"^t = {step / 30:.2f} s")

            def pick(label: str, option: str) -> None:
                page.get_by_label(label, exact=True).dispatch_event("click")
                page.get_by_role("option", name=option, exact=True).dispatch_event("click")
                page.wait_for_function("([l, o]) => [...document.querySelectorAll('input')].some("
                                       "i => i.value === o && i.id && document.querySelector(`label[for='${i.id}']`)"
                                       "?.textContent.trim() === l)", arg=[label, option], timeout=10000)

            # the boundaries found from the gripper and contacts, listed and drawn under the timeline
            page.get_by_text("Subtasks").first.wait_for(timeout=20000)
            shows(r"^cube steps 0-\d+ \(0\.00-")
            shows(r"not saved yet")
            first = re.search(r"cube steps 0-(\d+)", page.locator("li").first.text_content()).group(1)
            assert page.locator("div[title^='2: cube_base']").count() == 1  # the bar's second segment
            shows(r"cube \(1/2\)$")

            # move the boundary to the shown step, refuse one outside its neighbours, save
            go_to(100)
            assert int(first) != 100
            shows(r"cube_base \(2/2\)$")
            headless.click_button(page, "Move boundary here")
            shows(r"^cube steps 0-100 \(0\.00-3\.33 s\)")
            go_to(0)
            headless.click_button(page, "Move boundary here")
            shows(r"refused: boundary 1 must stay between steps 0 and 255")
            headless.click_button(page, "Save")
            shows(r"2 subtasks, saved to ")
            expected = [{"object": "cube", "start": 0, "end": 100}, {"object": "cube_base", "start": 100, "end": 255}]
            doc = json.loads(sidecar.read_text())
            assert doc["by"] == "human" and doc["subtasks"] == expected
            assert _inspect_subtasks(episode) == expected

            # type a step for the chosen boundary
            step_box = page.get_by_label("At step", exact=True)
            step_box.fill("90")
            shows(r"^cube steps 0-90 ")
            shows(r"not saved yet")

            # remove it, then add one back with its object picked from the scene's
            headless.click_button(page, "Remove boundary")
            shows(r"^cube steps 0-255 ")
            shows(r"cube \(1/1\)$")
            go_to(120)
            pick("Object", "cube")
            headless.click_button(page, "Add boundary here")
            shows(r"^cube steps 120-255 ")
            pick("Object", "cube_base")
            headless.click_button(page, "Set object here")
            shows(r"^cube_base steps 120-255 ")
            headless.click_button(page, "Save")
            shows(r"2 subtasks, saved to ")
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(20)
        log.close()
    assert code == 0, log_path.read_text()
    expected = [{"object": "cube", "start": 0, "end": 120}, {"object": "cube_base", "start": 120, "end": 255}]
    assert json.loads(sidecar.read_text())["subtasks"] == expected
    assert _inspect_subtasks(episode) == expected
