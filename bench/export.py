"""Export speed: offscreen rendering from replayed states, and the whole LeRobot export.

Figures (`measure`), on real recordings (lift, Panda, 30 Hz, the scripted pick):
  render_fps            frames/s per camera at 224x224 with the export's tuned renderer
                        (no shadows, no MSAA, no reflections, finite floor, buffer = image,
                        round primitives with facets for the image size);
                        includes mj_setState + mj_forward per frame; per camera the best
                        of 3 passes over the episode, then the median over front, overhead, wrist
  render_fps_default    the same with MuJoCo's own settings (shadows, 4x MSAA, reflections,
                        infinite floor, the model's 640x480 buffer, 28x16 facets), for comparison
  export_frames_per_s   `teleop export` end to end (replay, rendering front + wrist at
                        224x224, LeRobot add_frame/save_episode, H.264 video encoding (the
                        default codec), finalize) in dataset frames per second of wall time,
                        best of 2 runs
  export_frames_per_s_varied  the same episodes with --looks 2 --vary looks (each rendered twice, each time with
                        its own lights, colours, textures and camera jitter: scenes/vary/looks.py), in dataset
                        frames per second; runs alternate with the plain export's, best of as many
  export_frames_per_s_av1  the same with --vcodec av1 (LeRobot's default codec), one run
  export_frames_per_s_workers  the same episodes with --workers 2 (shards in spawned processes,
                        merged by LeRobot's aggregate_datasets), one run; timed as the single-process
                        figure is, from when the workers have loaded LeRobot to the merged dataset
  export_workers_wall_s  that export's whole wall time, worker start-up (spawn, imports) included
The GL backend is MUJOCO_GL if set, else EGL, else OSMesa (on a CPU both are Mesa llvmpipe).
The figures are taken in a fresh Python process, set up as `teleop export` sets itself up
(other benches in the same process would already have loaded OpenGL their own way).
"""

from __future__ import annotations

import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SCRIPT = ROOT / "scenes" / "scripts" / "lift_pick.json"
SIZE = (224, 224)


def record(directory: Path, episodes: int) -> list[Path]:
    """Record scripted lift episodes with the real CLI (what users export)."""
    cmd = [sys.executable, "-m", "teleop", "run", "--device", f"script:{SCRIPT}", "--scene", "lift",
           "--record", str(directory), "--episodes", str(episodes), "--no-verify", "--json"]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    if done.returncode != 0:
        raise RuntimeError(f"recording for the export bench failed: {done.stderr.strip()[-500:]}")
    return sorted(directory.glob("*.mcap"))


def render_rate(path: Path, cameras: list[str], settings, frames: int | None = None, repeats: int = 3) -> float:
    """Frames/s per camera rendering the episode's states (setState + forward + render + readback)."""
    from replay import load_episode, replay_states
    from replay.render import FastRenderer

    ep = load_episode(path)
    model = ep.build_model()
    best = []
    with FastRenderer(model, *SIZE, cameras, settings=settings) as renderer:
        for name in cameras:
            rates = []
            for _ in range(repeats):
                n = 0
                t0 = time.perf_counter()
                for k, data in replay_states(ep, model):
                    renderer.render(data, name)
                    n += 1
                    if frames is not None and n >= frames:
                        break
                rates.append(n / (time.perf_counter() - t0))
            best.append(max(rates))  # best of the repeats: other load on the machine only slows a run
    return statistics.median(best)


def export_rate(paths: list[Path], out: Path, vcodec: str | None = None, workers: int = 1, looks: int = 1) -> float:
    return export_run(paths, out, vcodec, workers, looks)[0]


def export_run(paths: list[Path], out: Path, vcodec: str | None = None, workers: int = 1, looks: int = 1) -> tuple[float, float]:
    """(frames/s as the export's summary times it, wall seconds of the whole call); looks > 1: that many varied looks."""
    from replay.export import ExportOptions
    from replay.export import export_dataset
    from scenes.vary.variation import GROUPS, Variation

    opts = ExportOptions(
        out=out, repo_id="bench/export", cameras=["front", "wrist"], image_size=SIZE, vcodec=vcodec, progress=False,
        workers=workers, looks=looks, variation=Variation(kinds=GROUPS["looks"]) if looks > 1 else None,
    )
    t0 = time.perf_counter()
    summary = export_dataset(paths, opts, log=lambda line: None)
    return summary.frames_per_s, time.perf_counter() - t0


def measure(quick: bool) -> dict[str, float]:
    """The figures, taken in a fresh process (see the module doc)."""
    cmd = [sys.executable, "-m", "bench.export"] + (["--quick"] if quick else [])
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"export bench failed: {done.stderr.strip()[-500:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def _measure(quick: bool) -> dict[str, float]:
    from teleop.cli.export import quiet_environment

    quiet_environment()  # as `teleop export`: no encoder banners or extra progress bars
    from replay.export.lerobot_io import load_lerobot
    from replay.render import DEFAULTS, TUNED

    with tempfile.TemporaryDirectory(prefix="bench_export_") as tmp:
        tmp = Path(tmp)
        paths = record(tmp / "episodes", 1 if quick else 3)
        cameras = ["front", "overhead", "wrist"]
        render = render_rate(paths[0], cameras, TUNED, repeats=1 if quick else 3)
        default = render_rate(paths[0], cameras, DEFAULTS, frames=10 if quick else 30, repeats=1)
        out = {"render_fps": round(render, 1), "render_fps_default": round(default, 1)}
        try:
            load_lerobot()
        except ValueError:  # LeRobot not installed: the export figures cannot be taken
            return out
        runs, varied = [], []
        for i in range(1 if quick else 2):  # alternating: the machine's speed drifts between runs
            runs.append(export_rate(paths, tmp / f"dataset{i}"))
            varied.append(export_rate(paths, tmp / f"dataset_varied{i}", looks=2))
        out["export_frames_per_s"] = round(max(runs), 1)
        out["export_frames_per_s_varied"] = round(max(varied), 1)
        out["export_frames_per_s_av1"] = round(export_rate(paths, tmp / "dataset_av1", vcodec="av1"), 1)
        rate, wall = export_run(paths, tmp / "dataset_workers", workers=2)
        out["export_frames_per_s_workers"] = round(rate, 1)
        out["export_workers_wall_s"] = round(wall, 1)
    return out


if __name__ == "__main__":
    print(json.dumps(_measure("--quick" in sys.argv)))
