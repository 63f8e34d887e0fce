"""Reviewing episodes (issue 36): the video, the review page's list, the quality flags.

Figures (`measure`), on one recorded lift episode (the scripted solution, 30 Hz):
  video_frames_per_s      frames rendered from the recorded states and encoded to H.264 per second,
                          `front` + `wrist` at 320x240 each with the overlay strip, median of 3 videos
                          after the first (their GL contexts lent warm by replay.render_pool, as the
                          review page renders one episode after another), in a process of its own set up
                          as `teleop video` and `teleop review` are; goal >= 200 on 2 cores
  video_frames_per_s_cold the first video of the process (each camera's GL context made for it: what
                          `teleop video` on one episode does)
  review_list_ms_1000     `GET /api/episodes` of the review server for a folder of 1,000 episodes whose
                          rows are cached (hard links to the one episode); goal <= 2,000
  quality_ms_per_episode  scoring one episode: the pass over its states, its success test, exact re-simulation
"""

from __future__ import annotations

import multiprocessing
import os
import statistics
import sys
import tempfile
import threading
import time
import urllib.request
from http.server import ThreadingHTTPServer
from pathlib import Path

import teleop
from replay.render import rasterize_in_render_threads
from replay.review.listing import make_row, store_row
from replay.review.quality import scores
from replay.review.video import VideoOptions, write_episodes
from teleop.web.shared.access import Gate
from teleop.web.review_page.server import ReviewFolder, make_handler

ROOT = Path(__file__).resolve().parent.parent
LIST_SIZE = 1000


def record(folder: Path) -> Path:
    session = teleop.Session(scene="lift", robot="panda", seed=0, control_hz=30)
    with teleop.Recorder(session, folder, formats=("mcap",), verify="off") as rec:
        teleop.run_episode(session, [teleop.ScriptDevice(ROOT / "scenes" / "scripts" / "lift_pick.json")])
    return rec.paths[0]


def list_ms(source: Path, folder: Path) -> float:
    """Milliseconds for the review server's list of LIST_SIZE episodes (rows already cached)."""
    folder.mkdir()
    row = make_row(teleop.load_episode(source))
    for i in range(LIST_SIZE):
        path = folder / f"episode_{i:06d}.mcap"
        os.link(source, path)
        store_row(path, dict(row, id=path.name, path=str(path)))
    server = ThreadingHTTPServer(("127.0.0.1", 0), make_handler(ReviewFolder(folder), Gate(None, 0), "bench"))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        url = f"http://127.0.0.1:{server.server_address[1]}/api/episodes"
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            with urllib.request.urlopen(url) as answer:
                assert answer.read().count(b'"id"') == LIST_SIZE
            times.append((time.perf_counter() - t0) * 1000.0)
        return statistics.median(times)
    finally:
        server.shutdown()
        server.server_close()


def video_rates(source: str, folder: str, runs: int) -> list[float]:
    """Frames per second of `runs` videos of the episode at `source`, one after another in this process."""
    rasterize_in_render_threads()
    episode = teleop.load_episode(source)
    options = VideoOptions(cameras=("front", "wrist"), size=(320, 240))
    return [write_episodes([episode], Path(folder) / f"v{i}.mp4", options)["frames_per_s"] for i in range(runs)]


def measure(quick: bool = False) -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        source = record(tmp / "one")
        episode = teleop.load_episode(source)
        # In a process of its own, as `teleop video` and `teleop review` render: llvmpipe set up for them
        # (replay.render.rasterize_in_render_threads), whatever the benches before this one rendered.
        with multiprocessing.get_context("spawn").Pool(1) as child:
            rates = child.apply(video_rates, (str(source), str(tmp), 2 if quick else 4))
        quality = []
        for _ in range(1 if quick else 3):
            t0 = time.perf_counter()
            scores(episode)
            quality.append((time.perf_counter() - t0) * 1000.0)
        listing = list_ms(source, tmp / "many")
    print(f"review: {episode.steps} steps; video {rates} frames/s", file=sys.stderr)
    return {
        "video_frames_per_s": round(statistics.median(rates[1:]), 1),
        "video_frames_per_s_cold": round(rates[0], 1),
        "review_list_ms_1000": round(listing, 1),
        "quality_ms_per_episode": round(statistics.median(quality), 1),
    }
