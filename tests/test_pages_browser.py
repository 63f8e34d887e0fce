"""Issue 49, items 2-5 in headless Chromium, on real episode files: the campaign's join and admin pages and
the review page share one stylesheet (served at /static/teleop.css without a token, readable on a phone);
the admin page plots successful episodes per hour (campaign and per operator) and each task's quota as a
bar; the review page's buttons write verdicts and notes; the admin and review pages show a banner while
their server is gone and take it away, with the state read again, when it is back.
"""

from __future__ import annotations

import getpass
import signal
import subprocess
import urllib.request
from pathlib import Path

import pytest

from devices.script import ScriptDevice
from replay.review.verdicts import read_verdict
from teleop.control.loop import run_episode
from teleop.control.recording import Recorder
from teleop.control.session import Session
from tests import browser as headless
from tests.support import CAMPAIGN_ADMIN, CAMPAIGN_JOIN, ROOT, popen_cli, wait_until

STYLESHEET = ROOT / "teleop" / "web" / "shared" / "static" / "teleop.css"
CAMPAIGN = 'name = "trial"\nout = "data"\nmax_sessions = 2\n[[task]]\nscene = "lift"\nepisodes = 5\n'
PAGE_BACKGROUND = "rgb(22, 22, 26)"  # the stylesheet's --bg: what a page without it does not have


def record(folder: Path, operator: str, seed: int, succeed: bool = True) -> None:
    """A real lift episode by `operator`: the pick script to the end (a success), or 5 ticks of it."""
    session = Session("lift", robot="panda", seed=seed)
    Recorder(session, folder, verify="off", provenance={"operator": operator, "campaign": "trial", "session": f"s-{operator}"})
    script = ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")
    script.start()
    assert run_episode(session, [script], max_steps=None if succeed else 5).success == succeed


@pytest.fixture(scope="module")
def campaign_file(tmp_path_factory) -> Path:
    """A campaign whose out/lift holds 3 successful episodes (ana 2, bo 1) and a failed one of ana."""
    work = tmp_path_factory.mktemp("pages")
    (work / "week.toml").write_text(CAMPAIGN)
    lift = work / "data" / "lift"
    for operator, seed, succeed in (("ana", 0, True), ("bo", 1, True), ("ana", 2, True), ("ana", 3, False)):
        record(lift, operator, seed, succeed)
    return work / "week.toml"


class Server:
    """`python -m teleop ARGS --port PORT` in a subprocess, ready once `ready(log)` holds; stopped as by Ctrl-C."""

    def __init__(self, args: list[str], port: int, log: Path, ready) -> None:
        self.args, self.port, self.log_path, self.ready = args, port, log, ready
        self.start()

    def start(self) -> None:
        self.log = open(self.log_path, "w")
        self.proc = popen_cli([*self.args, "--port", str(self.port)], self.log, cwd=ROOT)
        wait_until(lambda: self.proc.poll() is not None or self.ready(self), 120, f"teleop {self.args[0]} to answer")
        assert self.proc.poll() is None, self.log_path.read_text()

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)
            try:
                self.proc.wait(60)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def answers(url: str) -> bool:
    try:
        with urllib.request.urlopen(url, timeout=5) as answer:
            return answer.status == 200
    except OSError:
        return False


@pytest.fixture(scope="module")
def lobby(campaign_file):
    port = headless.free_port()
    server = Server(["campaign", str(campaign_file), "--token", CAMPAIGN_ADMIN, "--join-token", CAMPAIGN_JOIN], port,
                    campaign_file.parent / "campaign.log",
                    lambda s: answers(f"http://127.0.0.1:{s.port}/api/status?token={CAMPAIGN_ADMIN}"))
    yield server
    server.stop()


@pytest.fixture(scope="module")
def review(campaign_file):
    port = headless.free_port()
    server = Server(["review", str(campaign_file.parent / "data" / "lift")], port, campaign_file.parent / "review.log",
                    lambda s: "open http" in s.log_path.read_text())
    yield server
    server.stop()


def banner_shown(page) -> bool:
    return page.evaluate("!document.getElementById('banner').hidden && document.body.dataset.connection === 'lost'")


def test_the_three_pages_share_one_stylesheet_served_without_a_token(lobby, review, browser):
    for port in (lobby.port, review.port):  # the stylesheet itself: no token, the file as it is
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/static/teleop.css", timeout=10) as answer:
            assert answer.status == 200 and answer.headers["Content-Type"].startswith("text/css")
            assert answer.read() == STYLESHEET.read_bytes()
    pages = {"join": f"http://127.0.0.1:{lobby.port}/join?token={CAMPAIGN_JOIN}",
             "admin": f"http://127.0.0.1:{lobby.port}/admin?token={CAMPAIGN_ADMIN}",
             "review": f"http://127.0.0.1:{review.port}/"}
    page = browser.new_page(viewport={"width": 390, "height": 844})  # a phone's size
    try:
        for name, url in pages.items():
            page.goto(url, timeout=60_000)
            page.wait_for_function("document.styleSheets.length > 0 && document.styleSheets[0].cssRules.length > 20",
                                   timeout=30_000)
            sheets = page.evaluate("[...document.styleSheets].map((s) => s.href)")
            assert sheets == [f"{url.split('/')[0]}//{url.split('/')[2]}/static/teleop.css"], (name, sheets)
            assert page.evaluate("getComputedStyle(document.body).backgroundColor") == PAGE_BACKGROUND, name
            assert page.evaluate("document.querySelectorAll('style').length") == 0, name  # no copy of it inline
            if name != "review":  # readable on a phone: nothing wider than the screen
                assert page.evaluate("document.documentElement.scrollWidth <= window.innerWidth"), name
        page.goto(pages["join"], timeout=60_000)
        assert page.locator("#name").bounding_box()["height"] >= 40  # a field a finger can hit
    finally:
        page.close()


def test_the_admin_page_plots_successes_per_hour_and_each_quota(lobby, browser):
    page = browser.new_page(viewport={"width": 1100, "height": 900})
    try:
        page.goto(f"http://127.0.0.1:{lobby.port}/admin?token={CAMPAIGN_ADMIN}", timeout=60_000)
        page.wait_for_selector("body[data-ready='1'] #rate-plot g[data-series='campaign']", timeout=30_000)
        series = page.evaluate("""Object.fromEntries([...document.querySelectorAll('#rate-plot g[data-series]')]
            .map((g) => [g.dataset.series, g.dataset.values.split(',').map(Number)]))""")
        assert {key: sum(values) for key, values in series.items()} == {"campaign": 3, "operator:ana": 2, "operator:bo": 1}
        assert page.locator("#rate-plot polyline").count() == 3  # a line each, drawn in the page (inline SVG)
        legend = page.locator("#rate-legend li").all_inner_texts()
        assert legend == ["the campaign (3)", "ana (2)", "bo (1)"]
        bar = page.locator("#tasks tr[data-task='lift'] svg.bar")
        assert (bar.get_attribute("data-done"), bar.get_attribute("data-wanted")) == ("3", "5")
        assert float(bar.locator("rect.done").get_attribute("width")) == pytest.approx(200 * 3 / 5)
        assert "an hour" in page.locator("#forecast").inner_text()
        # live: a new success appears on the next refresh
        record(lobby.log_path.parent / "data" / "lift", "bo", 4)
        page.wait_for_function("""document.querySelector("#rate-plot g[data-series='operator:bo']").dataset.values
            .split(',').map(Number).reduce((a, b) => a + b, 0) === 2""", timeout=30_000)
        assert bar.get_attribute("data-done") == "4"
    finally:
        page.close()


def test_the_review_buttons_write_verdicts_and_notes(review, browser, campaign_file):
    lift = campaign_file.parent / "data" / "lift"
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    try:
        page.goto(f"http://127.0.0.1:{review.port}/", timeout=60_000)
        page.wait_for_selector("body[data-ready='1']", timeout=60_000)
        first, second = page.locator("#rows tr").nth(0).get_attribute("data-id"), page.locator("#rows tr").nth(1).get_attribute("data-id")
        page.get_by_role("button", name="Reject", exact=True).click()
        page.wait_for_selector(f"#rows tr[data-id='{first}'] td.verdict.reject", timeout=60_000)  # on the row at once
        page.wait_for_function("document.getElementById('status').textContent.includes('reject saved')", timeout=30_000)
        assert read_verdict(lift / first)["verdict"] == "reject"
        assert page.get_by_role("button", name="Reject", exact=True).get_attribute("aria-pressed") == "true"
        page.locator(f"#rows tr[data-id='{second}']").click()
        page.get_by_role("button", name="Accept", exact=True).click()
        page.wait_for_function("document.getElementById('status').textContent.includes('accept saved')", timeout=30_000)
        page.get_by_role("button", name="Note", exact=True).click()
        page.get_by_label("note on the selected episode").fill("the cube slips once")
        page.get_by_role("button", name="Save note", exact=True).click()
        page.wait_for_function("document.getElementById('status').textContent.includes('accept saved')"
                               " && document.querySelector('#rows tr.sel td.verdict').textContent.includes('✎')", timeout=30_000)
        written = read_verdict(lift / second)
        assert (written["verdict"], written["note"], written["reviewer"]) == ("accept", "the cube slips once", getpass.getuser())
    finally:
        page.close()


def test_admin_and_review_pages_show_a_banner_while_their_server_is_gone(lobby, review, browser, campaign_file):
    admin = browser.new_page(viewport={"width": 1100, "height": 800})
    reviewing = browser.new_page(viewport={"width": 1100, "height": 800})
    try:
        admin.goto(f"http://127.0.0.1:{lobby.port}/admin?token={CAMPAIGN_ADMIN}", timeout=60_000)
        reviewing.goto(f"http://127.0.0.1:{review.port}/", timeout=60_000)
        for page in (admin, reviewing):
            page.wait_for_selector("body[data-ready='1']", timeout=60_000)
            assert page.locator("#banner").is_hidden()
        lobby.stop()
        review.stop()
        for page in (admin, reviewing):
            page.wait_for_function("document.body.dataset.connection === 'lost'", timeout=30_000)
            assert banner_shown(page)
            assert "disconnected from the server: reconnecting" in page.locator("#banner").inner_text()
        # meanwhile a verdict is written from elsewhere: the page shows it once the server is back
        episode = sorted(p.name for p in (campaign_file.parent / "data" / "lift").glob("*.mcap"))[-1]
        from replay.review.verdicts import write_verdict

        write_verdict(campaign_file.parent / "data" / "lift" / episode, "reject", "ben", "")
        lobby.start()
        review.start()
        for page in (admin, reviewing):
            page.wait_for_function("document.body.dataset.connection === 'ok'", timeout=60_000)
            assert page.locator("#banner").is_hidden()
        reviewing.wait_for_selector(f"#rows tr[data-id='{episode}'] td.verdict.reject", timeout=30_000)
        assert admin.locator("#rate-plot g[data-series='campaign']").count() == 1
    finally:
        admin.close()
        reviewing.close()
