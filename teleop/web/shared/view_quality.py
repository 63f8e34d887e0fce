"""A 3D view a CPU can draw, for browsers whose WebGL runs in software.

A browser without a usable GPU (a VM or remote desktop, hardware acceleration
off, headless Chromium) draws WebGL with SwiftShader or llvmpipe on the page's
main thread, and keys, gizmo drags and panel clicks wait behind each frame.
Measured in headless Chromium at 1280x800 on 2 cores: viser's default look
(shadow maps of three cascades, the image-based environment light) takes
~0.8 s a frame and keeps the page drawing without pause, so a key waited
0.1-1 s; without shadows and the environment map a frame takes ~0.2 s and
an idle page draws once a second (viser's heartbeat), so most keys wait for
nothing.

Two changes, for such a browser only:
- before viser's code runs, a script in the page (`head_script`) asks viser to
  draw at half the display's resolution (its `fixedDpr` URL setting, which a
  user can also set by hand: `?fixedDpr=1` keeps full resolution). Frame time
  follows pixel count: with it a key reached the control tick in 26-44 ms (the
  bench's `browser_key_latency_ms`, a median that includes up to one 33 ms tick
  of waiting), against 100-130 ms at full resolution and 130-240 ms with viser's
  full look;
- the page reports its renderer (page_input.js, a `view` message) and the server
  changes that browser's scene through viser's per-client API: no shadows
  (teleop's bodies then cast none onto the floor), no environment map, and a
  directional light from behind the initial camera in its place, so that the
  faces the camera sees are lit.
Browsers with a GPU keep viser's look at full resolution.

Both 3D pages do this: the live session and the replay viewer (`teleop replay
--serve`), whose page runs the input channel's script only for its `view`
report and its lost-server banner (`ViewReports`).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable

import viser

from teleop.web.shared.camera_markers import CAMERA_LOOK_AT, CAMERA_POSITION
from teleop.web.shared.input_messages import InputMessage, View
from teleop.web.viser_internals.page_script import FIXED_DPR_PARAM

LIGHT_NAME = "/teleop/software_view_light"
LIGHT_INTENSITY = 2.0
SOFTWARE_DPR = 0.5  # device pixels per CSS pixel of the 3D view in a software-WebGL browser

# The renderer names viser's own "Software WebGL rendering detected" warning checks.
_HEAD = """<script>
(() => {  // teleop: a browser drawing WebGL without a GPU gets a lighter 3D view (teleop/web/shared/view_quality.py)
  let software = false;
  try {
    const canvas = document.createElement("canvas");
    const gl = canvas.getContext("webgl2") || canvas.getContext("webgl");
    if (gl) {
      const info = gl.getExtension("WEBGL_debug_renderer_info");
      const name = String(gl.getParameter(info ? info.UNMASKED_RENDERER_WEBGL : gl.RENDERER)).toLowerCase();
      software = ["swiftshader", "llvmpipe", "softpipe", "software"].some((s) => name.includes(s));
      const lose = gl.getExtension("WEBGL_lose_context");
      if (lose) lose.loseContext();
    }
  } catch (error) {
    software = false;
  }
  window.__teleopSoftwareGl = software;
  const params = new URLSearchParams(location.search);
  if (!software || params.has(__PARAM__)) return;
  params.set(__PARAM__, "__DPR__");  // read by viser when it starts, just after this
  history.replaceState(history.state, "", location.pathname + "?" + params.toString() + location.hash);
})();
</script>"""


def head_script() -> bytes:
    """The script put first in viser's page: find out how it draws, and draw less if on a CPU."""
    return _HEAD.replace("__PARAM__", json.dumps(FIXED_DPR_PARAM)).replace("__DPR__", repr(SOFTWARE_DPR)).encode()


def simplify(client: viser.ClientHandle) -> None:
    """Give this browser the cheap view: default lights without shadows, no environment map, a camera light."""
    scene = client.scene
    scene.configure_default_lights(True, cast_shadow=False)
    scene.configure_environment_map(hdri=None)
    # A three.js directional light shines from its position towards the origin of its parent:
    # put it at the camera, offset so that it points from the camera at what the camera looks at.
    position = tuple(p - t for p, t in zip(CAMERA_POSITION, CAMERA_LOOK_AT))
    scene.add_light_directional(LIGHT_NAME, intensity=LIGHT_INTENSITY, position=position, cast_shadow=False)


class SoftwareViews:
    """The clients of one viser server that draw in software, each given the cheap view once (thread-safe)."""

    def __init__(self, server: viser.ViserServer) -> None:
        self.server = server
        self._clients: set[int] = set()
        self._lock = threading.Lock()

    def __len__(self) -> int:
        with self._lock:
            return len(self._clients)

    def reported(self, client_id: int, software_gl: bool) -> bool:
        """A page said how it draws (network thread); a page drawing on a CPU gets `simplify`. True if it did now."""
        client = self.server.get_clients().get(client_id)
        if client is None or not software_gl:
            return False
        with self._lock:
            if client_id in self._clients:
                return False
            self._clients.add(client_id)
        simplify(client)
        return True

    def forget(self, client_id: int) -> None:
        """The client left (its id is never reused by viser; this keeps the count right)."""
        with self._lock:
            self._clients.discard(client_id)


class ViewReports:
    """The input channel's listener on a page that only reports how it draws (the replay viewer)."""

    def __init__(self, views: SoftwareViews, log: Callable[[str], None] | None = None) -> None:
        self.views = views
        self.log = log  # told when a page gets the lighter view

    def opened(self, conn: int, remote: str) -> None:
        pass

    def received(self, conn: int, message: InputMessage) -> None:
        """Only `view` counts here; the rest (hello, a blur's release) has nothing to act on."""
        if not isinstance(message, View) or message.client is None:
            return
        if self.views.reported(message.client, message.software_gl) and self.log is not None:
            self.log(f"a browser draws WebGL without a GPU: its view is drawn at {SOFTWARE_DPR:g}x resolution, "
                     "without shadows or the environment light")

    def quiet(self, conn: int) -> None:
        pass

    def closed(self, conn: int) -> None:
        pass
