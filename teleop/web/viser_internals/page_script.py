"""What viser's page (its client) does that teleop relies on: running our scripts, its URL parameter, its buttons,
and the message its 3D view sends when it opens.

- `run_javascript`: viser's client runs the source of a `RunJavascriptMessage`
  (`viser._messages`) with `Function(source)()` (viser's `add_plotly` uses it);
  it is queued on one client's connection (`ClientHandle._websock_connection`).
- `FIXED_DPR_PARAM`: the URL query parameter viser's client reads when it starts,
  the canvas' device pixels per CSS pixel.
- `GUI_BUTTON_SELECTOR`: a GUI button from `gui.add_button(label)` is a `<button>`
  element whose text is its label; page scripts (page_devices.js) find the panel's
  buttons by selector and label, both handed to them from Python.
- `viewer_camera_message`: viser's wire format for the page's first camera message.

Why viser needs these and what upstream change would retire them: the package's docstring
(teleop/web/viser_internals/__init__.py).
"""

from __future__ import annotations

import msgspec.msgpack
import viser
from viser._messages import RunJavascriptMessage

FIXED_DPR_PARAM = "fixedDpr"  # ?fixedDpr=0.5: viser's client draws its canvas at 0.5 device pixels per CSS pixel
GUI_BUTTON_SELECTOR = "button"  # the element a viser GUI button is drawn as; its text is the button's label


def run_javascript(client: viser.ClientHandle, source: str) -> None:
    """Run `source` in one browser's page (viser's client: `Function(source)()`), after what is queued before."""
    client._websock_connection.queue_message(RunJavascriptMessage(source=source))  # noqa: SLF001


def viewer_camera_message() -> bytes:
    """The message a page sends when its 3D view opens (msgpack, viser's ViewerCameraMessage). viser counts a
    client as connected, and sends it scene updates, from its first one: a client of the websocket that is not a
    browser (the campaign bench's watching pages) sends it to be watched like one."""
    return msgspec.msgpack.encode({
        "type": "ViewerCameraMessage", "wxyz": [1.0, 0.0, 0.0, 0.0], "position": [1.5, 0.0, 1.0], "fov": 0.9,
        "near": 0.01, "far": 100.0, "image_height": 600, "image_width": 800, "look_at": [0.0, 0.0, 0.0],
        "up_direction": [0.0, 0.0, 1.0]})
