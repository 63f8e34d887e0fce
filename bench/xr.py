"""XR page figures: an emulated Quest 3 (Meta's IWER in headless Chromium) driving `teleop serve` (lift, Panda, 30 Hz).

- `xr_to_tick_ms`: p95 from the start of the XR frame in which the right controller's pose changed to the
  control tick that applied it (the page stamps each pose with its frame's start, the server the tick; one
  machine, one clock), while the controller sweeps with the squeeze held. Goal: <= 45 ms.
- `xr_pose_hz`: body-pose messages a second the page received. Goal: >= the control rate (30).
- `xr_frame_ms`: the page's median time to draw one XR frame, both eyes, of the lift scene in software WebGL
  (SwiftShader; `gl.finish()` inside the timing), 1280 x 640: a figure to watch (a Quest draws on its GPU).

IWER comes from the cache `./run.sh test` fills (~/.cache/mujoco-teleop/iwer, or $TELEOP_IWER_CACHE); without it
or without Chromium the figures are not measured (an empty result, the reason on stderr).
"""

from __future__ import annotations

import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

IWER_VERSION = "2.5.0"
SWEEP = r"""
(() => {
  const c = window.__iwer.controllers.right, x0 = c.position.x, y0 = c.position.y, z0 = c.position.z, t0 = performance.now();
  c.updateButtonValue('squeeze', 1);
  window.__sweep = setInterval(() => {  // 2 cm circles at 0.5 Hz: a pose that changes every frame
    const a = (performance.now() - t0) / 1000 * Math.PI;
    c.position.set(x0 + 0.02 * Math.sin(a), y0 + 0.02 * Math.cos(a) - 0.02, z0);
  }, 5);
})();
"""


def _iwer() -> Path | None:
    cache = Path(os.environ.get("TELEOP_IWER_CACHE", Path.home() / ".cache" / "mujoco-teleop" / "iwer"))
    path = cache / IWER_VERSION / "package" / "build" / "iwer.min.js"
    return path if path.is_file() else None


def measure(quick: bool = False) -> dict[str, float]:
    from tests import browser as headless

    iwer = _iwer()
    if iwer is None or headless.chromium_path() is None:
        print("bench xr: needs Chromium and IWER (./run.sh test fetches it); not measured", file=sys.stderr)
        return {}
    from playwright.sync_api import sync_playwright

    window = 5.0 if quick else 15.0
    init = iwer.read_text(encoding="utf-8") + (
        "\n;(() => { const d = new IWER.XRDevice(IWER.metaQuest3, {stereoEnabled: true});"
        " d.installRuntime({forceInstall: true}); window.__iwer = d; })();\n")
    with tempfile.TemporaryDirectory(prefix="teleop-bench-xr-") as tmp, sync_playwright() as p:
        browser = headless.launch(p, msaa=True)  # as a user's browser draws
        server = headless.ServeProcess(["--device", "gizmo"], Path(tmp))
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 640})
            page.add_init_script(init)
            page.goto(server.url + "/xr", timeout=60000)
            page.wait_for_function("window.__xr && window.__xr.scenesReceived > 0", timeout=60000)
            page.get_by_text("Enter VR", exact=True).click()
            page.wait_for_function("window.__xr.drawnFrames > 5", timeout=60000)
            page.evaluate("window.__xr.measure = true; window.__xr.frameMs.length = 0")
            page.evaluate(SWEEP)
            time.sleep(1.0)
            first = server.status()
            poses0, t0 = page.evaluate("[window.__xr.posesReceived, performance.now()]")
            samples: list[float] = []
            end = time.monotonic() + window
            while time.monotonic() < end:  # the status keeps the newest 50: read it often enough to see them all
                time.sleep(1.0)
                samples += server.status()["xr"]["frame_to_tick_ms"]
            poses1, t1 = page.evaluate("[window.__xr.posesReceived, performance.now()]")
            frame_ms = page.evaluate("window.__xr.frameMs.slice()")
            last = server.status()
            page.close()
        finally:
            server.stop()
            browser.close()
    latencies = np.array(sorted(set(samples)))  # a sample read twice counts once
    if not latencies.size or last["xr"]["poses"] <= first["xr"]["poses"]:
        print("bench xr: the emulated controller's poses did not reach the session", file=sys.stderr)
        return {}
    return {
        "xr_to_tick_ms": round(float(np.percentile(latencies, 95)), 1),
        "xr_to_tick_median_ms": round(float(np.median(latencies)), 1),
        "xr_pose_hz": round((poses1 - poses0) / ((t1 - t0) / 1000.0), 1),
        "xr_frame_ms": round(float(np.median(frame_ms)), 2),
    }
