"""Issue 36: `teleop review DIR` driven by a real headless Chromium, as a reviewer would use it.

The page plays the selected episode's video, `r` rejects it, `j` moves on and `a` accepts the
next; the verdicts are in the sidecars at once, the API lists them, and `teleop export --accepted`
leaves the rejected episode out.
"""

from __future__ import annotations

import getpass
import json
import time
import urllib.request
from pathlib import Path

import pytest

from replay.review.verdicts import read_verdict
from tests import browser as headless
from tests.support import ROOT, popen_cli, run_cli, run_json


@pytest.fixture(scope="module")
def folder(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("review")
    run_json("run", "--device", f"script:{ROOT / 'scenes' / 'scripts' / 'lift_pick.json'}", "--scene", "lift",
             "--episodes", "2", "--record", str(work / "eps"), "--json")
    return work / "eps"


def start_review(folder: Path, port: int, log_path: Path):
    log = open(log_path, "w")
    proc = popen_cli(["review", str(folder), "--port", str(port)], log, cwd=ROOT)
    deadline = time.monotonic() + 120
    while "open http" not in log_path.read_text():
        assert proc.poll() is None and time.monotonic() < deadline, log_path.read_text()
        time.sleep(0.2)
    return proc


def test_review_page_plays_rejects_and_accepts_and_export_keeps_the_accepted(folder, tmp_path):
    import playwright.sync_api as playwright_api

    episodes = sorted(folder.glob("*.mcap"))
    assert len(episodes) == 2
    port = headless.free_port()
    proc = start_review(folder, port, tmp_path / "review.log")
    try:
        with playwright_api.sync_playwright() as p:
            browser = headless.launch(p)
            try:
                page = browser.new_page(viewport={"width": 1280, "height": 800})
                page.goto(f"http://127.0.0.1:{port}/", timeout=60_000)
                page.wait_for_selector("body[data-ready='1']", timeout=60_000)
                assert page.locator("#rows tr").count() == 2
                # the first episode is selected and its video plays (rendered on first view)
                page.wait_for_function("document.getElementById('player').readyState >= 2", timeout=120_000)
                page.wait_for_function("document.getElementById('player').currentTime > 0.3", timeout=60_000)
                assert page.evaluate("document.getElementById('player').duration") == pytest.approx(4.8, abs=0.1)
                page.keyboard.press("r")
                page.wait_for_function("document.getElementById('status').textContent.includes('reject saved')")
                page.keyboard.press("j")
                page.keyboard.press("a")
                page.wait_for_function("document.getElementById('status').textContent.includes('accept saved')")
                assert page.locator("td.verdict.reject").count() == 1 and page.locator("td.verdict.accept").count() == 1
            finally:
                browser.close()
        rejected, accepted = read_verdict(episodes[0]), read_verdict(episodes[1])
        assert rejected["verdict"] == "reject" and accepted["verdict"] == "accept"
        assert rejected["reviewer"] == accepted["reviewer"] == getpass.getuser()
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/episodes") as answer:
            listed = {row["id"]: row for row in json.loads(answer.read())}
        assert listed[episodes[0].name]["verdict"] == "reject" and listed[episodes[1].name]["verdict"] == "accept"
        assert listed[episodes[1].name]["quality"]["flags"] == [] and "jerk_p90" in listed[episodes[1].name]["quality"]["scores"]
        # a script records a verdict through the API as the keys do: another reviewer, the last write wins
        body = json.dumps({"episode": episodes[0].name, "verdict": "reject", "reviewer": "ben", "note": "drops"}).encode()
        request = urllib.request.Request(f"http://127.0.0.1:{port}/api/verdict", data=body,
                                         headers={"Content-Type": "application/json"})
        with urllib.request.urlopen(request) as answer:
            assert json.loads(answer.read())["reviewer"] == "ben"
        assert read_verdict(episodes[0])["reviewer"] == "ben" and read_verdict(episodes[0])["note"] == "drops"
    finally:
        proc.terminate()
        proc.wait(timeout=30)
    assert proc.returncode == 0
    for episode in episodes:  # the episode files themselves are never rewritten
        assert not list(folder.glob(f"{episode.name}.*.part"))
    # the export keeps what was accepted, and says what it left out
    out = tmp_path / "dataset"
    result = run_cli("export", str(folder), "--out", str(out), "--repo-id", "test/reviewed", "--accepted",
                     "--image-size", "32x32", "--cameras", "none")
    assert result.returncode == 0, result.stderr[-3000:]
    assert "exported 1 episode," in result.stdout and "skipped 1 not accepted" in result.stdout
    import pandas as pd

    table = pd.concat([pd.read_parquet(p) for p in sorted((out / "meta" / "episodes").rglob("*.parquet"))])
    assert list(table["review_verdict"]) == ["accept"] and list(table["review_reviewer"]) == [getpass.getuser()]
