"""viser's, mjviser's and websockets' internals, behind one door.

No module outside this folder uses a private name of theirs (tests/test_architecture.py fails on any
`x._name` of theirs elsewhere); tests/test_viser_contract.py checks each one against the installed
releases, which pyproject.toml pins. The modules, split by what they reach into:

- `serving_hooks.py`: viser's one `websockets` server: our handler and `process_request` around viser's
  (the token gate, our routes), our script first in viser's page, a message size limit, the subprotocol;
- `page_script.py`: viser's page: running a script of ours in it, its `fixedDpr` URL parameter, its
  GUI buttons' element, its first camera message;
- `scene_stream.py`: viser's scene updates: property sets collected per node in a block and written by
  us to the pages as one frame of viser's wire format;
- `casts.py`: viser's property cast, quicker for float arrays;
- `mjviser_poses.py`: mjviser's body handles and the poses they hold;
- `guarded_start.py`: `start_guarded`, viser's server started through `serving_hooks.wrapping_serve` with the
  gate's rules (teleop.web.shared.access, plain Python) in front of its handler, and `install()` applied.

`install()` applies the process-wide patches (`casts.install_quick_array_casts`, `scene_stream.collect_scene_updates`),
once, explicitly, where an app starts its viser server (teleop.web.viser_internals.guarded_start.start_guarded, which both
`teleop serve` and the replay viewer start through; the bench's own servers call it): never at import and never
in a constructor. `SceneStream()` refuses to start without it. `serving_hooks.wrapping_serve` is not process-wide:
it is a context manager around one `ViserServer()` construction (start_guarded again).

Why each exists, and the smallest upstream change that would retire it:

- `serving_hooks.wrapping_serve` (websockets' `serve` replaced while `ViserServer()` starts): viser has no auth
  hook, no Origin check and no way to add a route to its server. Upstream: a `process_request` (or `auth`)
  callable and extra websocket routes as `ViserServer(...)` arguments, passed on to `websockets.serve`.
- `serving_hooks.with_head_script`, `INDEX_PATHS` (our script spliced into viser's `index.html`): viser has no
  way to add a script to its page before its client starts. Upstream: a `ViserServer(head_html=...)` argument
  (or the `process_request` hook above, which would at least make this public).
- `serving_hooks.limit_message_size` (a connection's `protocol.max_message_size`): websockets fixes the limit at
  `serve(max_size=...)`, one for all paths, and viser sets 50 MB. Upstream (websockets): a public per-connection
  limit; or (viser) the route hook above taking its own `max_size`.
- `serving_hooks.WEBSOCKET_PROTOCOL`, `page_script.viewer_camera_message` (viser's subprotocol and wire format,
  spoken by the bench's pages that are not browsers): viser documents no client protocol. Upstream: the
  subprotocol as a public constant and a documented Python client (viser has none).
- `page_script.run_javascript` (`ClientHandle._websock_connection` and `viser._messages.RunJavascriptMessage`):
  viser runs page JavaScript only for its own plotly support. Upstream: a public `ClientHandle.run_javascript(source)`.
- `page_script.FIXED_DPR_PARAM`, `GUI_BUTTON_SELECTOR`: facts about viser's client (a URL parameter it reads, the
  element a button is), not documented. Upstream: document them, or a server-side `ViserServer(pixel_ratio=...)`
  and a stable `data-` attribute on GUI elements.
- `casts.install_quick_array_casts` (`AssignablePropsBase._cast_value_recursive` wrapped): viser builds
  `npt.NDArray[np.float16/32/64]` anew on every property set to compare with the hint (~20-35 us each).
  Upstream: build those three hints once at module level (or cache the per-property cast in `_prop_hints`).
- `scene_stream.collect_scene_updates`, `SceneStream`, `set_arrays`, `send_updates`
  (`SceneNodeHandle._queue_update`, `SceneApi._queue_scene_message`, `ViserServer.flush` wrapped; the broadcast
  buffer's cursors, the live connections and viser's wire format read and written): viser sends a message per
  property set through a sender task that wakes per window; `ViserServer.atomic()` only orders them. Upstream: a
  public batched update (`with server.batch():` that sends each node's changes as one message in one frame,
  written at the block's end) and a flush that writes at once.
- `mjviser_poses.pose_entries`, `stored_poses` (mjviser's `_mesh_groups`, `_any_decor_visible()`; a viser
  handle's `_impl.props`): mjviser updates every handle from `xmat` on each call and exposes neither its handles
  nor whether an overlay is on. Upstream (mjviser): public read access to its mesh groups (handle, body ids, mocap
  ids) and an `update_from_poses(xpos, xquat, mocap_pos, mocap_quat)` that takes MuJoCo's quaternions; (viser) a
  batched setter that writes several properties of a node in one message (which would retire `stored_poses` and
  `set_arrays`).
"""

from __future__ import annotations

import threading

from teleop.web.viser_internals.casts import install_quick_array_casts, quick_array_casts_installed
from teleop.web.viser_internals.scene_stream import collect_scene_updates, scene_updates_collected

_INSTALL_LOCK = threading.Lock()


def install() -> None:
    """Apply every process-wide patch of viser (idempotent, thread-safe): call where an app starts, before its
    scene is drawn."""
    with _INSTALL_LOCK:
        install_quick_array_casts()
        collect_scene_updates()


def installed() -> bool:
    """Whether every process-wide patch of install() is in place."""
    return quick_array_casts_installed() and scene_updates_collected()
