"""Issue 36: reviewing episodes: `teleop video`, quality flags, verdict sidecars, the review list.

Quick checks (verdicts, the flags' table and rules, the overlay, the PNG writer) run in-process;
what renders, encodes or records (the video decoded with PyAV, the flags of real bad and good
episodes) is e2e.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import zlib
from pathlib import Path

import numpy as np
import pytest

from replay.review.overlay import PENDING_RGB, STRIP_HEIGHT, SUCCESS_RGB, Overlay, StepInfo, Timeline
from replay.review.quality import FLAGS, THRESHOLDS, flags, long_outliers
from replay.review.verdicts import VerdictError, read_verdict, verdict_path, write_verdict
from tests.support import CAUSES, ROOT, assert_one_line_error, run_cli, run_json, small_fs, write_script

LIFT = [
    {"duration": 1.5, "to_body": "cube", "offset": [0, 0, 0.12], "gripper": "open"},
    {"duration": 1.0, "to_body": "cube", "offset": [0, 0, 0.0]},
    {"duration": 0.6, "gripper": "close"},
    {"duration": 1.2, "move": [0, 0, 0.15]},
]
BAD_SCRIPTS = {  # name -> (script steps, the flag it must raise)
    "jerky": (LIFT[:1] + [s for _ in range(15) for s in ({"duration": 0.1, "move": [0.03, 0, 0]},
                                                         {"duration": 0.1, "move": [-0.03, 0, 0]})] + LIFT[1:], "jerky"),
    "idle": (LIFT[:1] + [{"duration": 6.0}] + LIFT[1:] + [{"duration": 0.5}], "idle"),
    "dropped": (LIFT + [{"duration": 0.3, "gripper": "open"}, {"duration": 1.5}], "dropped"),  # let go in the air
}


# -- verdict sidecars ------------------------------------------------------------------------------


def test_a_verdict_goes_to_a_sidecar_and_the_episode_is_not_touched(tmp_path):
    episode = tmp_path / "episode_000000.mcap"
    episode.write_bytes(b"not really an episode")
    before = episode.stat().st_mtime_ns
    assert read_verdict(episode) is None
    written = write_verdict(episode, "reject", "ana", "cube slips")
    assert verdict_path(episode) == tmp_path / "episode_000000.mcap.review.json"
    assert read_verdict(episode) == written and written["verdict"] == "reject" and written["reviewer"] == "ana"
    assert written["note"] == "cube slips" and written["time"].endswith("+00:00")
    assert episode.read_bytes() == b"not really an episode" and episode.stat().st_mtime_ns == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_000000.mcap", "episode_000000.mcap.review.json"]


def test_a_bad_verdict_or_no_reviewer_is_refused(tmp_path):
    episode = tmp_path / "e.mcap"
    with pytest.raises(VerdictError, match="must be one of accept, reject"):
        write_verdict(episode, "maybe", "ana")
    with pytest.raises(VerdictError, match="reviewer"):
        write_verdict(episode, "accept", "  ")
    assert not verdict_path(episode).exists()


def test_two_reviewers_at_once_leave_one_whole_verdict_the_last_written(tmp_path):
    episodes = [tmp_path / f"e{i}.mcap" for i in range(2)]
    barrier = threading.Barrier(2)

    def review(name: str, verdict: str) -> None:
        barrier.wait()
        for _ in range(50):
            for ep in episodes:
                write_verdict(ep, verdict, name)

    threads = [threading.Thread(target=review, args=a) for a in (("ana", "accept"), ("ben", "reject"))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for ep in episodes:
        got = read_verdict(ep)
        assert (got["reviewer"], got["verdict"]) in {("ana", "accept"), ("ben", "reject")}
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".part")]
    write_verdict(episodes[0], "accept", "cy", "re-checked")
    assert read_verdict(episodes[0])["reviewer"] == "cy"


# -- the flags' rules ------------------------------------------------------------------------------


def test_the_thresholds_table_names_every_flag_once_and_the_docs_print_it():
    assert FLAGS == ("long", "idle", "jerky", "wandering", "tracking", "chatter", "dropped", "hard_contact", "failed",
                     "not_exact")
    docs = (ROOT / "docs" / "review.md").read_text()
    for t in THRESHOLDS:
        assert f"`{t.flag}`" in docs and f"`{t.score}`" in docs, t.flag


def test_flags_come_from_the_scores_and_the_table():
    clean = {"idle_fraction": 0.1, "jerk_p90": 10.0, "path_ratio": 1.2, "tracking_max_mm": 2.0, "rapid_toggles": 0,
             "drops": 0, "max_contact_n": 5.0, "success": True, "bit_exact": True}
    assert flags(clean) == []
    assert flags(clean, long=True) == ["long"]
    bad = dict(clean, idle_fraction=0.9, jerk_p90=5000.0, path_ratio=9.0, tracking_max_mm=500.0, rapid_toggles=4,
               drops=1, max_contact_n=2000.0, success=False, bit_exact=False)
    assert flags(bad) == [f for f in FLAGS if f != "long"]
    assert flags(dict(clean, bit_exact=None)) == []  # not checked is not flagged


def test_long_is_an_iqr_outlier_within_its_task():
    durations = {f"lift{i}": ("lift", s) for i, s in enumerate([10.0, 11.0, 10.5, 12.0, 30.0])}
    durations |= {"door0": ("door", 30.0), "door1": ("door", 31.0), "door2": ("door", 29.0)}  # 3: too few to judge
    assert long_outliers(durations) == {"lift4"}


# -- the overlay and the PNG writer -----------------------------------------------------------------


def test_the_overlay_badge_turns_green_on_success_and_the_bar_marks_subtasks():
    timeline = Timeline("Pick up the cube", 100, 10.0, [("cube", 0, 40), ("target", 40, 100)])
    overlay = Overlay(timeline, 400)
    before = overlay.strip(StepInfo(10, 1.0, 0, "operator (gizmo)", False))
    after = overlay.strip(StepInfo(80, 8.0, 1, "operator (gizmo)", True))
    assert before.shape == after.shape == (STRIP_HEIGHT, 400, 3)
    corner = (slice(16, 18), slice(400 - 20, 400 - 4))  # inside the badge, right of its text
    assert (before[corner] == PENDING_RGB).all() and (after[corner] == SUCCESS_RGB).all()
    bar_row = before[STRIP_HEIGHT - 4]
    assert (bar_row[160] == 255).all()  # the boundary at step 40 of 100 on a 400 px bar


def test_png_writer_makes_a_valid_png():
    from replay.review.listing import png

    image = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    data = png(image)
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    idat = data.index(b"IDAT")
    length = int.from_bytes(data[idat - 4:idat], "big")
    raw = zlib.decompress(data[idat + 4:idat + 4 + length])
    rows = [raw[r * 16 + 1:(r + 1) * 16] for r in range(4)]
    assert b"".join(rows) == image.tobytes()


# -- real episodes (e2e) ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def bad_episodes(tmp_path_factory) -> dict[str, Path]:
    work = tmp_path_factory.mktemp("bad")
    out = {}
    for name, (steps, _) in BAD_SCRIPTS.items():
        script = write_script(work / f"{name}.json", steps)
        run_json("run", "--device", f"script:{script}", "--scene", "lift", "--record", str(work / name), "--json")
        (out[name],) = sorted((work / name).glob("*.mcap"))
    return out


@pytest.fixture(scope="module")
def good_episode(tmp_path_factory) -> Path:
    work = tmp_path_factory.mktemp("good")
    run_json("run", "--device", f"script:{ROOT / 'scenes' / 'scripts' / 'lift_pick.json'}", "--scene", "lift",
             "--record", str(work), "--json")
    (path,) = sorted(work.glob("*.mcap"))
    return path


@pytest.mark.e2e
@pytest.mark.parametrize("name", sorted(BAD_SCRIPTS))
def test_deliberately_bad_episodes_are_flagged(bad_episodes, name):
    quality = run_json("inspect", str(bad_episodes[name]), "--json")["quality"]
    assert BAD_SCRIPTS[name][1] in quality["flags"], quality
    assert quality["scores"]["bit_exact"] is True


@pytest.mark.e2e
def test_the_scripted_solutions_of_the_built_in_tasks_are_not_flagged(tmp_path):
    """The scenes with scripts of their own; each library task's script is judged by tests/test_library.py's
    sweep, which runs it anyway."""
    import teleop
    from replay.review.listing import list_rows

    cases = [("stack", "panda", "stack_pick.json"), ("pick_place", "panda", "pick_place.json"),
             ("door", "panda", "door_push.json"), ("handover", "bimanual", "handover.json"),
             ("lift", "ur5e", "lift_pick.json"), ("lift", "panda", "lift_pick.json")]
    for i, (scene, robot, script) in enumerate(cases):
        path = ROOT / "scenes" / "scripts" / script
        session = teleop.Session(scene=scene, robot=robot, seed=0, control_hz=30)
        with teleop.Recorder(session, tmp_path / f"{i:02d}_{scene}", formats=("mcap",), verify="off") as rec:
            teleop.run_episode(session, [teleop.ScriptDevice(path)])
        rec.paths[0].rename(tmp_path / f"{i:02d}_{scene}_{robot}.mcap")
    rows = list_rows(tmp_path)
    assert len(rows) == len(cases)
    flagged = {r["id"]: (r["flags"], r["quality"]["scores"]) for r in rows if r["flags"]}
    assert not flagged, flagged


@pytest.mark.e2e
def test_the_video_has_a_frame_per_step_at_the_control_rate_and_turns_green_after_success(good_episode, tmp_path):
    import av

    out = tmp_path / "lift.mp4"
    result = run_json("video", str(good_episode), "--out", str(out), "--camera", "front,wrist", "--size", "160x120",
                      "--json")
    info = run_json("inspect", str(good_episode), "--json")
    steps, success_step = info["steps"], info["quality"]["scores"]["success_step"]
    assert result["frames"] == steps and result["width"] == 320 and result["height"] == 120 + STRIP_HEIGHT
    assert 0 < success_step < steps - 5
    with av.open(str(out)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264" and stream.codec_context.pix_fmt == "yuv420p"
        assert float(stream.average_rate) == pytest.approx(info["control_hz"])
        frames = [f.to_ndarray(format="rgb24") for f in container.decode(video=0)]
    assert len(frames) == steps
    badge = (slice(120 + 17, 120 + 29), slice(320 - 14, 320 - 6))  # inside the badge, right of its text

    def green(frame) -> bool:
        r, g, b = frame[badge].reshape(-1, 3).mean(axis=0)
        return g > 150 and r < 100 and b < 130

    assert not any(green(f) for f in frames[:success_step])
    assert all(green(f) for f in frames[success_step:])
    assert out.read_bytes()[:64].find(b"ftyp") > 0 and b"moov" in out.read_bytes()[:4096]  # faststart: index first


@pytest.mark.e2e
def test_a_grid_pads_the_shorter_episode_and_a_gif_is_written(bad_episodes, good_episode, tmp_path):
    import av

    grid = run_json("video", str(good_episode), str(bad_episodes["idle"]), "--out", str(tmp_path / "g.mp4"),
                    "--size", "64x48", "--camera", "front", "--grid", "--no-overlay", "--json")
    longest = max(run_json("inspect", str(p), "--json")["steps"] for p in (good_episode, bad_episodes["idle"]))
    assert grid["frames"] == longest and (grid["width"], grid["height"]) == (128, 48)
    gif = run_json("video", str(good_episode), "--out", str(tmp_path / "g.gif"), "--size", "64x48", "--fps", "10",
                   "--json")
    with av.open(str(tmp_path / "g.gif")) as container:
        assert sum(1 for _ in container.decode(video=0)) == gif["frames"]


@pytest.mark.e2e
def test_video_bad_input_is_one_line_and_exit_2(good_episode, tmp_path):
    assert_one_line_error(run_cli("video", str(tmp_path / "nothing"), "--out", str(tmp_path / "a.mp4")), "nothing")
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_one_line_error(run_cli("video", str(empty), "--out", str(tmp_path / "a.mp4")), "no episode files")
    assert_one_line_error(run_cli("video", str(good_episode), "--out", str(tmp_path / "a.mp4"), "--camera", "top"),
                          "unknown camera 'top'", "front")
    assert_one_line_error(run_cli("video", str(good_episode), "--out", str(tmp_path / "no" / "a.mp4")), "no such folder")
    assert_one_line_error(run_cli("video", str(good_episode), "--out", str(tmp_path / "a.avi")), ".mp4 or .gif")
    assert_one_line_error(run_cli("video", str(good_episode), "--out", str(tmp_path / "a.mp4"), "--size", "big"),
                          "--size")
    assert_one_line_error(run_cli("review", str(tmp_path / "nothing")), "not a folder of episodes")
    assert_one_line_error(run_cli("review", str(empty)), "no episode files")
    with small_fs(tmp_path, 48, 40_000) as fs:  # a full disk: the OS's words, and no part file left
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])}
        full = subprocess.run([sys.executable, "-m", "teleop", "video", str(good_episode), "--out", str(fs.path / "a.mp4")],
                              capture_output=True, text=True, timeout=300, env=env, cwd=ROOT, preexec_fn=fs.preexec())
        assert_one_line_error(full, str(fs.path / "a.mp4"))
        assert any(c in full.stderr for c in CAUSES), full.stderr
        assert not list(fs.path.iterdir())


# -- the review server's API and its gate -------------------------------------------------------------


@pytest.fixture(scope="module")
def short_folder(tmp_path_factory) -> Path:
    """One short recorded episode (9 steps), scored in-process."""
    import teleop

    folder = tmp_path_factory.mktemp("short")
    script = write_script(folder.parent / "short.json", [{"duration": 0.3, "move": [0.0, 0.0, 0.02]}])
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    with teleop.Recorder(session, folder, formats=("mcap",), verify="off"):
        teleop.run_episode(session, [teleop.ScriptDevice(script)])
    return folder


def test_the_api_lists_and_records_verdicts_behind_the_token(short_folder):
    import urllib.error
    import urllib.request
    from http.server import ThreadingHTTPServer

    from teleop.web.shared.access import Gate
    from teleop.web.review_page.server import ReviewFolder, make_handler

    token = "review-token-123"
    server = ThreadingHTTPServer(("127.0.0.1", 0), make_handler(ReviewFolder(short_folder), Gate(token, 0), "ana"))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    base = f"http://127.0.0.1:{server.server_address[1]}"

    def call(path: str, body: dict | None = None, headers: dict | None = None) -> tuple[int, dict]:
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(base + path, data=data, headers={"Content-Type": "application/json",
                                                                          **(headers or {})})
        try:
            with urllib.request.urlopen(request) as answer:
                return answer.status, json.loads(answer.read())
        except urllib.error.HTTPError as exc:
            text = exc.read()
            return exc.code, json.loads(text) if text.startswith(b"{") else {}

    try:
        assert call("/api/episodes")[0] == 403  # no token
        status, rows = call(f"/api/episodes?token={token}")
        (episode,) = sorted(short_folder.glob("*.mcap"))
        assert status == 200 and [r["id"] for r in rows] == [episode.name] and rows[0]["path"] == str(episode)
        assert rows[0]["verdict"] is None and set(rows[0]["quality"]) == {"flags", "scores"}
        verdict = {"episode": episode.name, "verdict": "accept", "reviewer": "ana", "note": "clean"}
        assert call("/api/verdict", verdict)[0] == 403
        assert call(f"/api/verdict?token={token}", verdict, {"Origin": "http://elsewhere.example"})[0] == 403
        assert call(f"/api/verdict?token={token}", {**verdict, "verdict": "maybe"})[0] == 400
        assert call(f"/api/verdict?token={token}", {**verdict, "episode": "../x.mcap"})[0] == 404
        status, written = call(f"/api/verdict?token={token}", verdict)
        assert status == 200 and written["verdict"] == "accept" and written["reviewer"] == "ana"
        assert read_verdict(episode)["note"] == "clean"
        assert call(f"/api/episodes?token={token}")[1][0]["verdict"] == "accept"
    finally:
        server.shutdown()
        server.server_close()
