"""Subtasks in `teleop replay PATH --serve`: listed on the timeline, a boundary moved, removed, added, saved."""

from __future__ import annotations

import contextlib
import io
import json
import re
import signal
import time
from pathlib import Path

import pytest

from replay.subtasks.sidecar import Subtask, sidecar_path
from replay.subtasks.edit import EditRefused, SubtaskEdits, even_split
from teleop.web.replay_page.subtasks import step_from_browser, timeline_html
from tests import browser as headless
from tests.support import popen_cli, run_json

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
    run_json("run", "--scene", "stack", "--device", f"script:{SCRIPT}", "--record", str(work / "eps"), "--json")
    (path,) = sorted((work / "eps").glob("*.mcap"))
    return path


def _inspect_subtasks(path: Path) -> list[dict] | None:
    return run_json("inspect", str(path), "--json")["subtasks"]


@contextlib.contextmanager
def viewer_page(episode: Path, log_path: Path):
    """`teleop replay EPISODE --serve` on a free port (its output in log_path) and a headless Chromium page on it,
    once its Subtasks panel is drawn; afterwards the viewer is stopped by Ctrl-C and must exit 0."""
    import playwright.sync_api as playwright_api  # the test extra installs it; Chromium comes from run.sh
    port = headless.free_port()
    with open(log_path, "w") as log:
        proc = popen_cli(["replay", str(episode), "--serve", "--port", str(port)], log)
    try:
        deadline = time.monotonic() + 60
        while "open http" not in log_path.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, f"the viewer did not start: {log_path.read_text()}"
            time.sleep(0.2)
        with playwright_api.sync_playwright() as p:
            browser = headless.launch(p)
            page = headless.open_page(browser, f"http://127.0.0.1:{port}", size=(900, 700))
            page.get_by_text("Subtasks").first.wait_for(timeout=60_000)
            yield page
            browser.close()
    finally:
        proc.send_signal(signal.SIGINT)
        code = proc.wait(20)
    assert code == 0, log_path.read_text()


def shows(page, pattern: str, timeout_s: float = 60.0) -> None:
    """Wait until some element's text matches the regex `pattern` (a loaded machine draws slowly)."""
    page.wait_for_function("(p) => [...document.querySelectorAll('*')]"
                           ".some(e => new RegExp(p).test(e.textContent.trim()))",
                           arg=pattern, timeout=timeout_s * 1000, polling=100)


def listed_line(page, pattern: str, timeout_s: float = 60.0) -> str:
    """The text of the first Subtasks line (an `li`) matching the regex `pattern`, once the page shows one (the
    page may draw it again meanwhile: after a reconnect viser clears the panel and the server sends it anew)."""
    return page.wait_for_function("(p) => { const li = [...document.querySelectorAll('li')]"
                                  ".find(e => new RegExp(p).test(e.textContent.trim()));"
                                  " return li ? li.textContent.trim() : null; }",
                                  arg=pattern, timeout=timeout_s * 1000, polling=100).json_value()


def go_to(page, step: int, hz: float = 30.0) -> None:
    """Show `step` (typed in the Step slider's box) and wait for the time line of an episode at `hz`."""
    box = page.locator("input.mantine-NumberInput-input:visible").first  # the Step slider's box
    box.fill(str(step))
    box.press("Enter")
    shows(page, rf"^t = {step / hz:.2f} s")


@pytest.mark.browser
def test_subtasks_are_edited_and_saved_in_the_browser(episode, tmp_path):
    sidecar = episode.with_name(episode.name + ".subtasks.json")
    assert not sidecar.exists()
    log_path = tmp_path / "replay.log"
    with viewer_page(episode, log_path) as page:
        # the boundaries found from the gripper and contacts, listed and drawn under the timeline
        shows(page, r"^cube steps 0-\d+ \(0\.00-")
        shows(page, r"not saved yet")
        first = re.search(r"cube steps 0-(\d+)", listed_line(page, r"^cube steps 0-\d+")).group(1)
        page.wait_for_function("() => document.querySelectorAll(\"div[title^='2: cube_base']\").length === 1",
                               timeout=60_000)  # the bar's second segment
        shows(page, r"cube \(1/2\)$")

        # move the boundary to the shown step, refuse one outside its neighbours, save
        go_to(page, 100)
        assert int(first) != 100
        shows(page, r"cube_base \(2/2\)$")
        headless.click_button(page, "Move boundary here")
        shows(page, r"^cube steps 0-100 \(0\.00-3\.33 s\)")
        go_to(page, 0)
        headless.click_button(page, "Move boundary here")
        shows(page, r"refused: boundary 1 must stay between steps 0 and 255")
        headless.click_button(page, "Save")
        shows(page, r"2 subtasks, saved to ")
        expected = [{"object": "cube", "start": 0, "end": 100}, {"object": "cube_base", "start": 100, "end": 255}]
        doc = json.loads(sidecar.read_text())
        assert doc["by"] == "human" and doc["subtasks"] == expected
        assert _inspect_subtasks(episode) == expected

        # type a step for the chosen boundary
        step_box = page.get_by_label("At step", exact=True)
        step_box.fill("90")
        shows(page, r"^cube steps 0-90 ")
        shows(page, r"not saved yet")

        # remove it, then add one back with its object picked from the scene's
        headless.click_button(page, "Remove boundary")
        shows(page, r"^cube steps 0-255 ")
        shows(page, r"cube \(1/1\)$")
        go_to(page, 120)
        headless.pick(page, "Object", "cube")
        headless.click_button(page, "Add boundary here")
        shows(page, r"^cube steps 120-255 ")
        headless.pick(page, "Object", "cube_base")
        headless.click_button(page, "Set object here")
        shows(page, r"^cube_base steps 120-255 ")
        headless.click_button(page, "Save")
        shows(page, r"2 subtasks, saved to ")
    expected = [{"object": "cube", "start": 0, "end": 120}, {"object": "cube_base", "start": 120, "end": 255}]
    assert json.loads(sidecar.read_text())["subtasks"] == expected
    assert _inspect_subtasks(episode) == expected


HANDOVER = REPO / "scenes" / "scripts" / "handover.json"  # the left arm lifts the cube, the right takes it over


@pytest.fixture(scope="module")
def two_arm_episode(tmp_path_factory) -> Path:
    """A recorded `handover` (bimanual robot, seed 0, 30 Hz), annotated per arm by `teleop annotate --auto`."""
    import teleop
    from teleop.cli.entry import main

    work = tmp_path_factory.mktemp("two_arm")
    session = teleop.Session(scene="handover", robot="bimanual", seed=0, control_hz=30)
    with teleop.Recorder(session, work, verify="off") as rec:
        result = teleop.run_episode(session, [teleop.ScriptDevice(HANDOVER)])
    assert result.success
    (path,) = rec.paths
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["annotate", str(path), "--auto", "--json"]) == 0
    assert json.loads(out.getvalue())["episodes"][0]["by"] == "auto"
    return path


def listed(page, lines: int) -> None:
    """Wait until the Subtasks listing has `lines` lines (one per subtask of the arm being edited)."""
    page.wait_for_function("(n) => document.querySelectorAll('li').length === n", arg=lines, timeout=60_000)


def on_bar(page, *segments: str) -> None:
    """Wait until the timeline bar is exactly these segments ('i: object, steps a-b', its titles)."""
    page.wait_for_function("(want) => { const got = [...document.querySelectorAll('div[title]')].map(d => d.title)"
                           ".filter(t => /^\\d+: .*, steps \\d+-\\d+$/.test(t));"
                           " return JSON.stringify(got) === JSON.stringify(want); }", arg=list(segments), timeout=60_000)


@pytest.mark.browser
def test_each_arms_subtasks_are_edited_on_their_own_in_the_browser(two_arm_episode, tmp_path):
    episode = two_arm_episode
    sidecar = sidecar_path(episode)
    before = json.loads(sidecar.read_text())
    steps = before["steps"]
    left = [s for s in before["subtasks"] if s["arm"] == "left"]
    right = [s for s in before["subtasks"] if s["arm"] == "right"]
    assert [s["object"] for s in left] == ["cube", "world"] and [s["object"] for s in right] == ["cube"]
    grasped = left[0]["end"]  # the left arm's one boundary
    added, moved = 200, 250  # the right arm gets a boundary at step 200, then moves it to 250
    assert steps > moved + 1 and grasped not in (added, moved)
    log_path = tmp_path / "replay.log"
    with viewer_page(episode, log_path) as page:
        # the panel starts on the left arm: its two stored subtasks, listed and on the bar
        shows(page, rf"^cube steps 0-{grasped} \(0\.00-")
        shows(page, rf"^world steps {grasped}-{steps} ")
        shows(page, rf"^2 subtasks, from {re.escape(sidecar.name)}")
        listed(page, 2)
        on_bar(page, f"1: cube, steps 0-{grasped}", f"2: world, steps {grasped}-{steps}")
        shows(page, r"cube \(1/2\)$")

        # the right arm: its one subtask, nothing of the left arm's
        headless.pick(page, "Arm", "right")
        shows(page, r"editing the right arm.s subtasks")  # markdown may curl the apostrophe
        shows(page, rf"^cube steps 0-{steps} \(0\.00-")
        listed(page, 1)
        on_bar(page, f"1: cube, steps 0-{steps}")
        shows(page, r"cube \(1/1\)$")

        # give it a boundary, move that to the shown step, save
        go_to(page, added)
        headless.pick(page, "Object", "world")
        headless.click_button(page, "Add boundary here")
        shows(page, rf"^world steps {added}-{steps} ")
        go_to(page, moved)
        headless.click_button(page, "Move boundary here")
        shows(page, rf"^cube steps 0-{moved} \({0:.2f}-{moved / 30:.2f} s\)")
        shows(page, rf"^world steps {moved}-{steps} ")
        shows(page, r"world \(2/2\)$")
        on_bar(page, f"1: cube, steps 0-{moved}", f"2: world, steps {moved}-{steps}")
        headless.click_button(page, "Save")
        shows(page, r"^2 subtasks, saved to ")

        # back on the left arm: its subtasks as they were
        headless.pick(page, "Arm", "left")
        shows(page, r"editing the left arm.s subtasks")
        shows(page, rf"^cube steps 0-{grasped} \(0\.00-")
        shows(page, rf"^world steps {grasped}-{steps} ")
        listed(page, 2)
        on_bar(page, f"1: cube, steps 0-{grasped}", f"2: world, steps {grasped}-{steps}")
    expected = [*left, {"object": "cube", "start": 0, "end": moved, "arm": "right"},
                {"object": "world", "start": moved, "end": steps, "arm": "right"}]
    doc = json.loads(sidecar.read_text())
    assert doc["by"] == "human" and doc["steps"] == steps and doc["subtasks"] == expected
    assert _inspect_subtasks(episode) == expected
