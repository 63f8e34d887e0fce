"""The viser and websockets internals teleop relies on are there, in the installed releases.

teleop/web/viser_internals/ is the one folder that uses them (its package docstring lists each, with
the upstream change that would retire it); pyproject.toml pins viser to the minor versions this file
passes on. When a release changes one, the failing test says what changed and which teleop feature
it breaks, so that raising the pin is a matter of running this file (and fixing the module of
teleop/web/viser_internals/ it names where it fails).

Most checks run on a real ViserServer started through `wrapping_serve` and reached
with raw HTTP and websockets; the client bundle is read from viser's installed
`client/build`. One test opens the page in the system's headless Chromium
(Playwright) to see the browser side work (it fails without Chromium, as every browser test does).
"""

from __future__ import annotations

import gzip
import html
import importlib
import inspect
import re
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import viser
import websockets.asyncio.server
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from teleop.web.session_page.page_devices import CONNECT_SPACEMOUSE
from teleop.web.viser_internals import install
from teleop.web.viser_internals.page_script import FIXED_DPR_PARAM, GUI_BUTTON_SELECTOR, run_javascript
from teleop.web.viser_internals.serving_hooks import INDEX_PATHS, limit_message_size, with_head_script, wrapping_serve
from tests import browser as headless
from tests.support import wait_until

VISER_PROTOCOL = f"viser-v{viser.__version__}"
CLIENT_BUILD = Path(viser.__file__).resolve().parent / "client" / "build"
LIMIT_PATH = "/contract/limit"  # a websocket path of ours, beside viser's, with a small message limit
LIMIT_BYTES = 1024
# Put first in viser's page: marks that it ran, and asks for half resolution when the URL says `half`.
HEAD = (b"<script>window.__contractHead = true; (() => { const p = new URLSearchParams(location.search);"
        b" if (!p.has('half')) return; p.set('" + FIXED_DPR_PARAM.encode() + b"', '0.5');"
        b" history.replaceState(null, '', location.pathname + '?' + p.toString()); })();</script>")


# The 3D view: the largest canvas that has pixels (viser's page also has an empty one of the same size).
SCENE_CANVAS = ("[...document.querySelectorAll('canvas')].filter((c) => c.width > 0 && c.clientWidth > 0)"
                ".sort((a, b) => b.clientWidth * b.clientHeight - a.clientWidth * a.clientHeight)[0]")


def broken(what: str, breaks: str) -> str:
    """The failure message: what changed in the installed viser, and what of teleop's it breaks."""
    return (f"viser {viser.__version__} / websockets {websockets.__version__}: {what}. This breaks {breaks}. "
            "Adapt teleop/web/viser_internals/ (the only place that relies on it) or keep the pin in pyproject.toml.")


@dataclass(repr=False)  # a failing assert would print viser's page headers
class Served:
    """A plain ViserServer started through `wrapping_serve`, and what the wrap saw."""

    server: viser.ViserServer
    url: str
    starts: list[bool]
    passed: list[tuple] = field(default_factory=list)  # (handler, process_request) as viser passed them
    viser_pages: list[tuple[str, dict]] = field(default_factory=list)  # (path, headers) of viser's own page answers
    sockets: list[str] = field(default_factory=list)  # paths of websockets our handler saw
    limit_closed: list[int | None] = field(default_factory=list)  # close codes of the limited path
    limit_settable: list[bool] = field(default_factory=list)  # the connection had the limit to set


@pytest.fixture(scope="module")
def served():
    cache: dict = {}
    seen: dict = {}

    def wrap(handler, process_request):
        served_ = seen["served"]
        served_.passed.append((handler, process_request))

        async def our_handler(connection):
            path = urlsplit(connection.request.path).path
            served_.sockets.append(path)
            if path != LIMIT_PATH:
                await handler(connection)
                return
            served_.limit_settable.append(hasattr(getattr(connection, "protocol", None), "max_message_size"))
            limit_message_size(connection, LIMIT_BYTES)
            try:
                async for _ in connection:
                    pass
            except ConnectionClosed as exc:
                served_.limit_closed.append(exc.sent.code if exc.sent is not None else None)

        async def our_process_request(connection, request):
            response = process_request(connection, request) if process_request is not None else None
            if inspect.isawaitable(response):
                response = await response
            path = urlsplit(request.path).path
            if response is not None and path in INDEX_PATHS and response.status_code == 200:
                served_.viser_pages.append((path, dict(response.headers.raw_items())))
                response = with_head_script(response, HEAD, cache)
            return response

        return our_handler, our_process_request

    port = headless.free_port()
    seen["served"] = Served(server=None, url=f"http://127.0.0.1:{port}", starts=[])  # type: ignore[arg-type]
    original = websockets.asyncio.server.serve
    with wrapping_serve(wrap) as starts:
        server = viser.ViserServer(host="127.0.0.1", port=port, verbose=False)
    assert websockets.asyncio.server.serve is original, "wrapping_serve must put websockets' serve back"
    out = seen["served"]
    out.server, out.starts = server, starts
    server.gui.add_button(CONNECT_SPACEMOUSE)
    yield out
    server.stop()


def _get(url: str, **headers: str) -> tuple[dict, bytes]:
    with urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=30) as response:
        return dict(response.headers.items()), response.read()


# -- the server side ------------------------------------------------------------------
def test_viser_starts_its_server_through_websockets_serve_which_we_wrap(served):
    assert served.starts, broken(
        "ViserServer() no longer starts its server by calling websockets.asyncio.server.serve at start",
        "the session token, the Origin check and the page input channel (teleop.web.shared.access refuses to start)")
    assert len(served.passed) == 1
    handler, process_request = served.passed[0]
    assert callable(handler) and callable(process_request), broken(
        "viser no longer passes its websocket handler first and its page server as process_request= to serve",
        "the token gate, which wraps both")
    assert served.server.get_port() == int(urlsplit(served.url).port or 0), broken(
        "ViserServer moved to another port than the one asked for", "the printed URL")


def test_viser_answers_its_page_at_the_index_paths_in_html_gzipped_when_asked(served):
    for encoding in ("gzip", "identity"):
        served.viser_pages.clear()
        headers, body = _get(served.url + "/", **{"Accept-Encoding": encoding})
        assert served.viser_pages, broken("viser's process_request no longer answers GET / with its page",
                                          "the script put first in the page (view_quality's lighter view)")
        path, viser_headers = served.viser_pages[-1]
        assert "text/html" in viser_headers.get("Content-Type", ""), broken(
            f"viser's page is served as {viser_headers.get('Content-Type')!r}, not text/html",
            "with_head_script, which edits HTML answers only")
        zipped = viser_headers.get("Content-Encoding") == "gzip"
        assert zipped == (encoding == "gzip"), broken(
            f"viser's page for Accept-Encoding {encoding} came with Content-Encoding "
            f"{viser_headers.get('Content-Encoding')!r}", "with_head_script, which unzips gzip answers only")
        page = gzip.decompress(body) if headers.get("Content-Encoding") == "gzip" else body
        assert page.count(b"<head>") == 1, broken("viser's page has no single plain <head> tag",
                                                  "the script put first in the page")
        assert page.split(b"<head>", 1)[1].startswith(HEAD)  # ours, before any of viser's scripts
        assert int(headers["Content-Length"]) == len(body)
    assert (CLIENT_BUILD / "index.html").read_bytes().count(b"<head>") == 1


def test_a_client_handle_queues_messages_on_its_connection_and_the_message_class_is_there(served):
    messages = importlib.import_module("viser._messages")
    cls = getattr(messages, "RunJavascriptMessage", None)
    assert cls is not None, broken("viser._messages.RunJavascriptMessage is gone",
                                   "run_javascript: the page's key, gamepad and SpaceMouse scripts")
    assert "source" in inspect.signature(cls).parameters and cls(source="1").source == "1", broken(
        "RunJavascriptMessage no longer takes source=", "run_javascript")
    # viser registers a ClientHandle after its page's first camera message: the browser test below sends one
    # and runs a script through it; here, the parts it is made of.
    init = inspect.getsource(viser.ClientHandle.__init__)
    assert re.search(r"self\._websock_connection\s*=", init), broken(
        "viser.ClientHandle no longer keeps its connection in _websock_connection",
        "run_javascript: the page's key, gamepad and SpaceMouse scripts")
    connection_cls = getattr(importlib.import_module("viser.infra"), "WebsockClientConnection", None)
    queue = getattr(connection_cls, "queue_message", None)
    assert queue is not None and list(inspect.signature(queue).parameters) == ["self", "message"], broken(
        "viser.infra.WebsockClientConnection.queue_message(message) is gone or takes other arguments",
        "run_javascript")
    with connect(served.url.replace("http://", "ws://") + "/", subprotocols=[VISER_PROTOCOL], open_timeout=10) as ws:
        assert ws.recv(timeout=10)  # viser's first message, through our wrapped handler
    assert "/" in served.sockets


def test_our_message_size_limit_closes_a_connection_that_sends_a_bigger_frame(served):
    why = "limit_message_size: the input channel's frames would be bounded by viser's 50 MB, not MAX_FRAME"
    with connect(served.url.replace("http://", "ws://") + LIMIT_PATH, open_timeout=10) as ws:
        ws.send(b"x" * (LIMIT_BYTES // 2))
        wait_until(lambda: served.limit_settable, 15.0, "our handler to take the connection")
        assert served.limit_settable == [True], broken(
            "a websockets ServerConnection has no protocol.max_message_size to set", why)
        ws.send(b"x" * (LIMIT_BYTES * 4))
        try:
            ws.recv(timeout=10)
        except ConnectionClosed:
            pass
        else:
            pytest.fail(broken("a frame over protocol.max_message_size did not close the connection", why))
    wait_until(lambda: served.limit_closed, 15.0, "the limited connection to close")
    assert served.limit_closed == [1009], broken(
        f"a frame over the limit closed with code {served.limit_closed}, not 1009 (message too big)",
        "the input channel's frame limit")


# -- the client bundle -------------------------------------------------------------------
def client_code() -> str:
    """viser's client JavaScript as the browser gets it: plain scripts, or the bundle packed into index.html
    (viser 1.1: base-88 text in `<script data-p=...>`, zstd-compressed, styles then code: data-ss, data-cs)."""
    page = (CLIENT_BUILD / "index.html").read_text(encoding="utf-8")
    scripts = [page, *(p.read_text(encoding="utf-8", errors="replace") for p in CLIENT_BUILD.rglob("*.js"))]
    packed = re.search(r'<script data-p="([^"]*)"[^>]*?data-ss="(\d+)"[^>]*?data-cs="(\d+)"[^>]*>(.*?)</script>',
                       page, re.S)
    if packed is not None:
        import zstandard  # a viser dependency

        alphabet = re.search(r'const A="((?:[^"\\]|\\.)*)"', packed.group(4))
        assert alphabet is not None, broken("viser's packed client bundle has no alphabet (const A=...) any more",
                                            "this test's reading of the bundle")
        letters = alphabet.group(1).replace("\\\\", "\\")
        value = {c: i for i, c in enumerate(letters)}
        text, base = html.unescape(packed.group(1)), len(letters)
        data = bytearray()
        for start in range(0, len(text) - len(text) % 5, 5):
            number = 0
            for c in text[start:start + 5]:
                number = number * base + value[c]
            data += number.to_bytes(4, "big")
        if rest := len(text) % 5:
            number = 0
            for c in text[len(text) - rest:]:
                number = number * base + value[c]
            data += number.to_bytes(rest - 1, "big")
        styles, code = int(packed.group(2)), int(packed.group(3))
        raw = zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=styles + code)
        scripts.append(raw[styles:].decode("utf-8", errors="replace"))
    return "\n".join(scripts)


@pytest.fixture(scope="module")
def bundle() -> str:
    return client_code()


def test_the_client_reads_the_fixed_dpr_url_parameter(bundle):
    assert re.search(r"\.get\(([\"'`])" + re.escape(FIXED_DPR_PARAM) + r"\1\)", bundle), broken(
        f"viser's client no longer reads the {FIXED_DPR_PARAM!r} URL parameter (searchParams.get)",
        "view_quality: a browser drawing WebGL on the CPU would draw at full resolution")


def test_the_client_runs_run_javascript_messages_as_functions(bundle):
    assert re.search(r"RunJavascriptMessage[\"'`]?\s*:\s*(?:new\s+)?Function\(", bundle), broken(
        "viser's client no longer runs a RunJavascriptMessage's source with Function(source)()",
        "run_javascript: the page's key, gamepad and SpaceMouse scripts")


# -- in a browser ---------------------------------------------------------------------------
@pytest.mark.browser
def test_in_a_browser_the_head_script_fixed_dpr_scripts_and_button_labels_work(served):
    from playwright import sync_api as playwright_api

    with playwright_api.sync_playwright() as p:
        browser = headless.launch(p)
        try:
            before = set(served.server.get_clients())
            page = headless.open_page(browser, served.url + "/?half", size=(800, 600))
            assert page.evaluate("window.__contractHead === true")
            # The head script asked for half resolution before viser's client read the URL.
            page.wait_for_function(f"() => ({SCENE_CANVAS}) !== undefined", timeout=60000)
            ratio = page.evaluate(f"() => {{ const c = {SCENE_CANVAS}; return c.width / c.clientWidth; }}")
            assert page.evaluate("window.devicePixelRatio") == 1
            assert abs(ratio - 0.5) < 0.05, broken(
                f"with ?{FIXED_DPR_PARAM}=0.5 set by a script first in the page, viser's canvas has "
                f"{ratio:.2f} device pixels per CSS pixel, not 0.5",
                "view_quality's lighter view for software WebGL")
            # A script sent to this page's client runs in the page.
            client = wait_until(lambda: [c for i, c in served.server.get_clients().items() if i not in before],
                                15.0, "the page's client")[-1]
            run_javascript(client, "window.__contractRan = 6 * 7;")
            try:
                page.wait_for_function("window.__contractRan === 42", timeout=60000)
            except playwright_api.TimeoutError:
                pytest.fail(broken("a RunJavascriptMessage queued on the client's connection did not run in the page",
                                   "the page's key, gamepad and SpaceMouse scripts"))
            # A GUI button is an element matching GUI_BUTTON_SELECTOR whose text is its label.
            found = f"""() => [...document.querySelectorAll({GUI_BUTTON_SELECTOR!r})]
                          .some((b) => b.textContent.trim() === {CONNECT_SPACEMOUSE!r})"""
            try:
                page.wait_for_function(found, timeout=60000)
            except playwright_api.TimeoutError:
                pytest.fail(broken(f"gui.add_button({CONNECT_SPACEMOUSE!r}) is not drawn as a "
                                   f"{GUI_BUTTON_SELECTOR!r} element with that text",
                                   "page_devices.js, which asks for a WebHID SpaceMouse on that button's click"))
            page.close()
        finally:
            browser.close()


def test_quick_array_casts_cast_as_viser_does_and_scene_handles_take_them():
    """viser's property cast still compares hints with npt.NDArray[float...] (what the table stands for), and with
    quick_array_casts a handle's properties come out as they did: the same dtypes and values, other hints unchanged."""
    import numpy as np
    from viser._assignable_props_api import AssignablePropsBase

    from teleop.web.viser_internals.casts import FLOAT_ARRAY_HINTS, install_quick_array_casts

    original = getattr(AssignablePropsBase._cast_value_recursive, "original", AssignablePropsBase._cast_value_recursive)
    source = inspect.getsource(original)
    for name in ("float16", "float32", "float64"):
        assert f"npt.NDArray[np.{name}]" in source, broken(
            f"AssignablePropsBase._cast_value_recursive no longer special-cases npt.NDArray[np.{name}]",
            "install_quick_array_casts (scene updates would cast differently from viser)")
    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        axes = server.scene.add_batched_axes("/c", batched_wxyzs=np.tile([1.0, 0, 0, 0], (2, 1)),
                                             batched_positions=np.zeros((2, 3)))
        values = [np.arange(6.0).reshape(2, 3), [[1, 2, 3]], (0.5, 0.25, 0.125, 1.0), (np.ones(2), np.zeros(2))]
        hints = [*FLOAT_ARRAY_HINTS, tuple[float, ...], tuple[np.ndarray, ...], int]
        expected = [[original(axes, h, v, "batched_positions") for v in values] for h in hints]
        install_quick_array_casts()
        install_quick_array_casts()  # once per process: a second call keeps the first wrapper
        cast = AssignablePropsBase._cast_value_recursive
        assert getattr(cast, "quick", False) and cast.original is original
        for h, row in zip(hints, expected):
            for v, want in zip(values, row):
                got = cast(axes, h, v, "batched_positions")
                assert type(got) is type(want)
                assert np.asarray(got).dtype == np.asarray(want).dtype and np.array_equal(np.asarray(got), np.asarray(want))
        axes.batched_positions = np.ones((2, 3))  # float64 in: the handle's own dtype kept
        assert axes.batched_positions.dtype == np.float32 and np.all(axes.batched_positions == 1.0)
    finally:
        server.stop()


def test_body_poses_and_one_update_send_what_mjviser_and_viser_would():
    """BodyPoses (our update of mjviser's handles) leaves every body handle as mjviser's update_from_mjdata does
    (the same positions, the same rotations up to a quaternion's sign), takes the fast path on our pages' scene,
    and inside SceneStream.update a node's properties go out as one message; a second, unchanged update sends
    none; mjviser's own update (the fallback) goes out through the block as one message per node as well."""
    import mujoco
    import numpy as np
    from mjviser import ViserMujocoScene
    from viser._messages import SceneNodeUpdateMessage

    import teleop
    from teleop.web.session_page.body_poses import BodyPoses
    from teleop.web.viser_internals.scene_stream import SceneStream

    session = teleop.Session(scene="lift", robot="panda", seed=0)
    model = session.controller.model
    data = mujoco.MjData(model)
    data.qpos[:] = session.controller.data.qpos
    data.qpos[:7] += np.linspace(0.1, 0.7, 7)  # every link somewhere else than at the start
    mujoco.mj_kinematics(model, data)
    servers = [viser.ViserServer(host="127.0.0.1", port=0, verbose=False) for _ in range(2)]
    try:
        scenes = [ViserMujocoScene(server, model, num_envs=1) for server in servers]
        for scene in scenes:
            scene.camera_tracking_enabled = False
        scenes[0].update_from_mjdata(data)  # mjviser's own
        ours = BodyPoses(scenes[1])
        assert ours.entries, broken("mjviser's ViserMujocoScene no longer has the handles BodyPoses reads",
                                    "the cheap scene update (it falls back to mjviser's, about 3 times the CPU)")
        queued: list = []
        install()  # as an app's start does (teleop.web.shared.access.start_guarded)
        stream = SceneStream(servers[1])
        stream._send = queued.extend  # what the block hands on to be written to the pages
        buffer = servers[1]._websock_server._broadcast_buffer
        push = buffer.push
        buffer.push = lambda message: (queued.append(message), push(message))[1]  # and what goes to viser's buffer
        with stream.update():
            ours.update(data)
        theirs = [g.handle for g in scenes[0]._mesh_groups]
        mine = [g.handle for g in scenes[1]._mesh_groups]
        assert len(theirs) == len(mine) > 5
        moved = 0
        for a, b in zip(theirs, mine):
            assert np.allclose(a.batched_positions, b.batched_positions, atol=1e-6)
            dots = np.abs(np.sum(a.batched_wxyzs.astype(float) * b.batched_wxyzs.astype(float), axis=1))
            assert np.allclose(dots, 1.0, atol=1e-5), f"{a.name}: rotations differ"
            moved += not np.allclose(b.batched_positions, 0.0)
        assert moved > 5
        updates = [m for m in queued if isinstance(m, SceneNodeUpdateMessage)]
        names = [m.name for m in updates]
        assert len(names) == len(set(names)) and len(updates) >= 5, "one message per node"
        assert any(set(m.updates) == {"batched_positions", "batched_wxyzs"} for m in updates)
        queued.clear()
        with stream.update():
            ours.update(data)
        assert not [m for m in queued if isinstance(m, SceneNodeUpdateMessage)], "an unchanged pose is sent again"
        # A hidden node is not given poses; shown again, it gets the ones it missed though nothing moved since.
        hand, bodies, _ = next(e for e in ours.entries if e[0].visible and "/hand/" in e[0].name)  # moves with qpos
        hand.visible = False
        data.qpos[:7] += 0.1
        mujoco.mj_kinematics(model, data)
        queued.clear()
        with stream.update():
            ours.update(data)
        names = [m.name for m in queued if isinstance(m, SceneNodeUpdateMessage)]
        assert hand.name not in names and len(names) >= 5
        hand.visible = True
        queued.clear()
        with stream.update():
            ours.update(data)
        (shown,) = [m for m in queued if isinstance(m, SceneNodeUpdateMessage)]
        assert shown.name == hand.name and set(shown.updates) == {"batched_positions", "batched_wxyzs"}
        assert np.allclose(hand.batched_positions, data.xpos[bodies], atol=1e-6)
        queued.clear()
        # mjviser's own update (BodyPoses' fallback) through viser's setters: one message per node as well
        data.qpos[:7] -= 0.2
        mujoco.mj_kinematics(model, data)
        with stream.update():
            scenes[1].update_from_mjdata(data)
        names = [m.name for m in queued if isinstance(m, SceneNodeUpdateMessage)]
        assert len(names) >= 5 and len(names) == len(set(names)), "viser's setters: a message per property"
    finally:
        for server in servers:
            server.stop()


# -- scene frames written straight to the pages (SceneStream) ---------------------------
def decode_frame(raw: bytes) -> tuple[list[dict], list[bytes]]:
    """One websocket frame of viser's wire format: its messages (msgpack dicts) and its binary buffers."""
    import msgspec.msgpack
    import zstandard

    inner_size, packed_size = int.from_bytes(raw[:8], "little"), int.from_bytes(raw[8:16], "little")
    document = msgspec.msgpack.decode(
        zstandard.ZstdDecompressor().decompress(raw[16:16 + packed_size], max_output_size=inner_size))
    offset, buffers = 16 + packed_size, []
    for length in document["binaryBufferLengths"]:
        offset += (8 - offset % 8) % 8
        buffers.append(raw[offset:offset + length])
        offset += length
    assert offset == len(raw)
    return document["messages"], buffers


def frames_until(ws, wanted, timeout_s: float = 15.0) -> list[tuple[list[dict], list[bytes]]]:
    """Frames a raw client of viser's websocket receives until one holds a message `wanted(message)` is true of."""
    frames, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            raw = ws.recv(timeout=max(0.05, deadline - time.monotonic()))
        except TimeoutError:
            break
        frames.append(decode_frame(raw))
        if any(wanted(m) for m in frames[-1][0]):
            return frames
    pytest.fail(f"no frame with the wanted message in {timeout_s:.0f} s ({len(frames)} frames)")


def frames_for(ws, seconds: float) -> list[tuple[list[dict], list[bytes]]]:
    """Every frame a raw client of viser's websocket receives in `seconds`."""
    frames, deadline = [], time.monotonic() + seconds
    while (left := deadline - time.monotonic()) > 0:
        try:
            frames.append(decode_frame(ws.recv(timeout=left)))
        except TimeoutError:
            break
    return frames


def test_scene_stream_frames_are_viser_s_wire_format_after_the_nodes_and_whole_for_a_new_page(served):
    """SceneStream writes its updates itself: each page gets them as frames of viser's own format (header, zstd'd
    msgpack, aligned arrays), after the frames that made the nodes, once each and not again from viser's buffer;
    a page that opens later gets the whole newest state; a quick serialization equals viser's."""
    import numpy as np
    from viser._messages import SceneNodeUpdateMessage

    from teleop.web.viser_internals.scene_stream import SceneStream, serializable, set_arrays

    server = served.server
    axes = server.scene.add_batched_axes("/contract/stream_axes", batched_wxyzs=np.tile([1.0, 0, 0, 0], (2, 1)),
                                         batched_positions=np.zeros((2, 3)))
    gizmo = server.scene.add_transform_controls("/contract/stream_gizmo", position=(0.0, 0.0, 0.0))
    install()  # as an app's start does (teleop.web.shared.access.start_guarded)
    stream = SceneStream(server)
    url = served.url.replace("http://", "ws://")
    updated = lambda m: m.get("type") == "SceneNodeUpdateMessage" and m.get("name") == "/contract/stream_axes"  # noqa: E731
    with connect(url, subprotocols=[VISER_PROTOCOL], max_size=None) as first:
        made = frames_until(first, lambda m: m.get("name") == "/contract/stream_gizmo")  # viser's sender: the nodes
        assert not any(updated(m) for frame in made for m in frame[0])
        wait_until(lambda: stream.watched(), 10.0, "the page's connection")
        positions = np.array([[0.1, 0.2, 0.3], [0.4, 0.5, 0.6]], dtype=np.float32)
        for attempt in range(50):  # the page gets frames once viser's sender has written it the nodes
            with stream.update():
                set_arrays(axes, batched_positions=positions + attempt)
                gizmo.position = (0.5, 0.0, float(attempt))
            if stream.frames:
                break
            time.sleep(0.1)
        assert stream.frames, broken("SceneStream never found the page caught up with viser's sender",
                                     "the campaign's scene updates (none reach a page)")
        messages, buffers = [frame for frame in frames_for(first, 1.0) if any(updated(m) for m in frame[0])][-1]
        update = next(m for m in messages if updated(m))
        placeholder = update["updates"]["batched_positions"]
        assert placeholder["dtype"] == "<f4"
        sent = np.frombuffer(buffers[placeholder["__binary_index"]], dtype=np.float32).reshape(2, 3)
        assert np.allclose(sent, positions + attempt)
        pose = next(m for m in messages if m.get("name") == "/contract/stream_gizmo")
        assert pose["type"] == "SetPositionMessage" and list(pose["position"]) == [0.5, 0.0, float(attempt)]
        assert np.allclose(axes.batched_positions, positions + attempt)  # the handle holds what was sent
        # Nothing of it also went through viser's buffer: no second copy follows.
        final = positions - 1.0  # unlike any sent so far (the loop above may have stopped at attempt 0)
        with stream.update():
            set_arrays(axes, batched_positions=final)
        server.flush()  # were it in viser's buffer too, its sender would send it now
        again = frames_for(first, 1.0)
        assert sum(updated(m) for frame in again for m in frame[0]) == 1, "an update went out twice"
        # A page that opens now gets the newest state whole at the next update, though nothing changed since.
        with connect(url, subprotocols=[VISER_PROTOCOL], max_size=None) as second:
            frames_until(second, lambda m: m.get("name") == "/contract/stream_gizmo")  # viser's sender: the nodes
            for _ in range(50):
                with stream.update():
                    pass
                whole = [frame for frame in frames_for(second, 0.2) if any(updated(m) for m in frame[0])]
                if whole:
                    break
            assert whole, "a page that opened later never got the newest state"
            messages, buffers = whole[0]
            update = next(m for m in messages if updated(m))
            sent = np.frombuffer(buffers[update["updates"]["batched_positions"]["__binary_index"]], dtype=np.float32)
            assert np.allclose(sent.reshape(2, 3), final)
            pose = next(m for m in messages if m.get("name") == "/contract/stream_gizmo")
            assert list(pose["position"]) == [0.5, 0.0, float(attempt)]
            assert not [f for f in frames_for(first, 0.3) if any(updated(m) for m in f[0])], "the first page got it again"
    message = SceneNodeUpdateMessage("/n", {"batched_positions": positions, "batched_wxyzs": np.ones((2, 4))},
                                     owner="o")
    ours, theirs = [], []
    assert serializable(message, ours) == message.as_serializable_dict(theirs)
    assert [bytes(b) for b in ours] == [bytes(b) for b in theirs]
    axes.remove()
    gizmo.remove()


# -- installed once, explicitly -------------------------------------------------------
INSTALL_PROBE = '''
import json, threading
import viser
from viser._assignable_props_api import AssignablePropsBase
from viser._scene_api import SceneApi
from viser._scene_handles import SceneNodeHandle
import teleop.web.replay_page.viewer, teleop.web.session_page.app, teleop.web.session_page.serve  # every page
from teleop.web.viser_internals import install, installed
from teleop.web.viser_internals.scene_stream import SceneStream

def patched():
    return {"cast": getattr(AssignablePropsBase._cast_value_recursive, "quick", False),
            "queue_update": getattr(SceneNodeHandle._queue_update, "coalescing", False),
            "flush": getattr(viser.ViserServer.flush, "quiet_in_updates", False),
            "scene_message": getattr(SceneApi._queue_scene_message, "collecting", False)}

out = {"imported": patched(), "installed_before": installed()}
server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
try:
    SceneStream(server)
except RuntimeError as exc:
    out["refused"] = str(exc)
threads = [threading.Thread(target=install) for _ in range(8)]
for t in threads: t.start()
for t in threads: t.join()
first = (AssignablePropsBase._cast_value_recursive, SceneNodeHandle._queue_update, viser.ViserServer.flush,
         SceneApi._queue_scene_message)
install()
out["after"] = patched()
out["installed_after"] = installed()
out["same_wrappers"] = first == (AssignablePropsBase._cast_value_recursive, SceneNodeHandle._queue_update,
                                 viser.ViserServer.flush, SceneApi._queue_scene_message)
out["wrapped_once"] = all(not any(getattr(f.original, k, False) for k in ("quick", "coalescing", "quiet_in_updates", "collecting"))
                          for f in first)
SceneStream(server)  # now it starts
server.stop()
print(json.dumps(out))
'''


@pytest.mark.e2e
def test_viser_internals_are_installed_only_by_install_once_and_a_scene_stream_needs_it():
    """Issue 48: importing every page patches nothing of viser's; install() (from eight threads at once, then again)
    patches each method once; a SceneStream refuses to start before it."""
    import json
    import subprocess
    import sys

    root = Path(__file__).resolve().parent.parent
    result = subprocess.run([sys.executable, "-c", INSTALL_PROBE], cwd=root, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout.strip().splitlines()[-1])
    assert not any(out["imported"].values()), f"patched at import: {out['imported']}"
    assert out["installed_before"] is False
    assert "install()" in out.get("refused", ""), "SceneStream started without viser's scene updates collected"
    assert all(out["after"].values()) and out["installed_after"] is True, out["after"]
    assert out["same_wrappers"] and out["wrapped_once"]
