"""The page's input channel without a browser: message checks, key sources, and the channel on a real websocket."""

from __future__ import annotations

import asyncio
import json
import threading
import time

import numpy as np
import pytest
from websockets.asyncio.client import connect
from websockets.asyncio.server import serve

from devices.keyboard import KEY_ACTION, KeyState
from teleop.web.shared import input_channel
from teleop.web.shared.input_channel import BURST, MAX_FRAME, PATH, QUIET_S, InputChannel
from teleop.web.shared.input_messages import (
    MAX_BYTES, Hello, Key, Rejected, ReleaseAll, View, binding_name, browser_keys, parse,
)
from teleop.web.session_page.page_keyboard import PageKeyboardDevice, PageKeys
from tests.support import wait_until


def test_valid_messages_parse_into_their_types():
    assert parse('{"type": "key", "key": "W", "down": true}') == Key("w", True)
    assert parse('{"type": "key", "key": " ", "down": false}') == Key("space", False)
    assert parse('{"type": "key", "key": "+", "down": true}') == Key("=", True)  # shift+= speeds up too
    assert parse('{"type": "hello", "client": 3, "agent": "Mozilla/5.0"}') == Hello(3, "Mozilla/5.0")
    assert parse('{"type": "hello", "agent": ""}') == Hello(None, "")
    assert parse('{"type": "release_all", "why": "blur"}') == ReleaseAll("blur")
    assert parse('{"type": "view", "client": 2, "software_gl": true}') == View(2, True)
    assert parse('{"type": "view", "software_gl": false}') == View(None, False)


MALFORMED = [
    b'{"type": "key", "key": "w", "down": true}',  # a binary frame
    "not json",
    "[1, 2]",
    '{"type": "key", "key": "w", "down": true, "extra": 1}',
    '{"type": "key", "key": "w"}',
    '{"type": "key", "key": "x", "down": true}',  # not bound
    '{"type": "key", "key": "w", "down": 1}',
    '{"type": "key", "key": ["w"], "down": true}',
    '{"type": "hello", "client": NaN, "agent": ""}',
    '{"type": "hello", "client": 1e400, "agent": ""}',
    '{"type": "hello", "client": -1, "agent": ""}',
    '{"type": "hello", "client": true, "agent": ""}',
    '{"type": "hello", "client": 99999999999999999999, "agent": ""}',
    '{"type": "hello", "agent": "' + "x" * 300 + '"}',
    '{"type": "release_all", "why": "because"}',
    '{"type": "view", "client": 2, "software_gl": "yes"}',
    '{"type": "view", "client": 2}',
    '{"type": "view", "client": -2, "software_gl": true}',
    '{"type": "fly"}',
    '{"type": null}',
    '{"type": "ping"}',
    '{"type": "key", "key": "w", "down": true}' + " " * MAX_BYTES,
    "[" * 5000 + "]" * 5000,
]


@pytest.mark.parametrize("raw", MALFORMED, ids=range(len(MALFORMED)))
def test_malformed_messages_are_rejected_with_a_one_line_reason(raw):
    with pytest.raises(Rejected) as rejected:
        parse(raw)
    assert str(rejected.value) and "\n" not in str(rejected.value)


def test_the_page_catches_exactly_the_bound_keys():
    names = {binding_name(k) for k in browser_keys()}
    assert names == set(KEY_ACTION) - {"+"}  # "+" arrives as its own key and maps to "="
    assert binding_name("+") == "=" and binding_name("Enter") == "enter" and binding_name("x") is None
    assert {"w", "W", " ", "Tab", "Backspace", "Enter", "=", "+", "-"} <= set(browser_keys())


def test_a_key_held_by_two_sources_moves_once_and_until_both_let_go():
    state = KeyState(now=0.0)
    state.press("w", 0.0)  # this machine's keyboard...
    state.press("w", 0.01, "page:1")  # ...and the browser on the same desktop: one press
    state.release("w", 0.5)
    held, presses = state.take(1.0)
    assert presses == ["w"] and held == {"w": pytest.approx(1.0)}  # the page still holds it
    assert state.holding() == {"page:1": ["w"]} and state.last_source == "page:1"
    state.press("a", 1.2, "page:2")
    assert state.release_source("page:1", 1.5) == ["w"]
    held, _ = state.take(2.0)
    assert held["w"] == pytest.approx(0.5) and held["a"] == pytest.approx(0.8)
    state.release("a", 2.1, "page:1")  # a stray release from a page that does not hold it
    assert state.holding() == {"page:2": ["a"]}


def test_page_keys_drive_the_keyboard_device_and_let_go_when_told():
    device = PageKeyboardDevice(pos_speed=0.2, rot_speed=1.0)
    keys = PageKeys(device)
    keys.opened(1, "10.0.0.7")
    keys.received(1, Hello(4, "Mozilla/5.0 (X11) Chrome/131.0 Safari/537.36"))
    device.poll(None, 1 / 30)  # start of a tick
    keys.received(1, Key("w", True))
    keys.received(1, Key("j", True))
    time.sleep(0.2)
    (command,) = device.poll(None, 1 / 30)
    np.testing.assert_allclose(command.translation, [0.2 / 30, 0, 0], rtol=0.05)
    np.testing.assert_allclose(command.rotation, [0, 0, 1.0 / 30], rtol=0.05)
    assert command.source == "page keyboard"
    state = keys.state()
    assert state["driving"] == "browser 4 (10.0.0.7, Chrome 131)" and state["held"][state["driving"]] == ["j", "w"]
    assert "driving: browser 4" in device.status() and "holding j w" in device.status()
    keys.quiet(1)  # the connection stopped answering pings
    assert keys.state()["held"] == {} and keys.state()["last_release"] == "quiet"
    device.poll(None, 1 / 30)
    time.sleep(0.1)
    assert device.poll(None, 1 / 30) == []
    keys.received(1, Key("space", True))
    keys.received(1, Key("space", False))
    (command,) = device.poll(None, 1 / 30)
    assert command.gripper == "toggle"
    keys.received(1, Key("s", True))
    keys.release_client(4)  # viser's socket of that page closed
    assert keys.state()["held"] == {} and keys.state()["last_release"] == "viser closed"
    keys.received(1, Key("s", True))
    keys.closed(1)
    assert keys.state() == {"browsers": 0, "driving": None, "held": {}, "releases": 3, "last_release": "closed"}


class Recorder:
    """An InputListener that keeps what it is told."""

    def __init__(self) -> None:
        self.events: list[tuple] = []

    def opened(self, conn, remote):
        self.events.append(("opened", conn))

    def received(self, conn, message):
        self.events.append(("received", message))

    def quiet(self, conn):
        self.events.append(("quiet", conn))

    def closed(self, conn):
        self.events.append(("closed", conn))


@pytest.fixture
def channel():
    """An InputChannel served by a plain websockets server on a thread (viser's part is tested elsewhere)."""
    listener = Recorder()
    chan = InputChannel(listener)
    loop = asyncio.new_event_loop()
    ready = threading.Event()
    stop: list[asyncio.Event] = []
    port: list[int] = []

    async def main():
        stop.append(asyncio.Event())
        async with serve(chan.handle, "127.0.0.1", 0) as server:
            port.append(server.sockets[0].getsockname()[1])
            ready.set()
            await stop[0].wait()

    thread = threading.Thread(target=lambda: loop.run_until_complete(main()), daemon=True)
    thread.start()
    assert ready.wait(10)
    yield chan, listener, f"ws://127.0.0.1:{port[0]}{PATH}"
    loop.call_soon_threadsafe(stop[0].set)
    thread.join(5)


def test_the_channel_passes_valid_messages_and_drops_and_counts_the_rest(channel):
    chan, listener, url = channel

    async def talk():
        async with connect(url) as ws:
            await ws.send(json.dumps({"type": "key", "key": "w", "down": True}))
            for raw in MALFORMED:
                await ws.send(raw)
            await ws.send(json.dumps({"type": "key", "key": "w", "down": False}))
            await asyncio.sleep(0.3)

    asyncio.run(talk())
    assert wait_until(lambda: ("closed", 1) in listener.events, 30.0)
    received = [e[1] for e in listener.events if e[0] == "received"]
    assert received == [Key("w", True), Key("w", False)]
    assert chan.dropped == len(MALFORMED) and chan.accepted == 2 and chan.last_drop


def test_the_channel_limits_rate_and_frame_size(channel):
    chan, listener, url = channel

    sent = int(BURST) + 3000  # past the burst by 10 s of the sustained rate: drops even if a busy machine reads slowly

    async def flood():
        async with connect(url, max_size=None) as ws:
            for _ in range(sent):
                await ws.send('{"type": "release_all", "why": "blur"}')
            await asyncio.sleep(0.5)
            await ws.send("x" * (MAX_FRAME + 1))
            await ws.wait_closed()
            return ws.close_code

    start = time.monotonic()
    code = asyncio.run(flood())
    elapsed = time.monotonic() - start  # the server read the flood within this
    assert code == 1009  # message too big: the connection is closed...
    assert wait_until(lambda: chan.accepted + chan.dropped >= sent, 30.0)
    assert chan.accepted <= BURST + input_channel.RATE * elapsed + 1  # ...and past the burst, no more than the rate
    assert chan.dropped >= 150
    assert wait_until(lambda: chan.connections == 0, 30.0)
    assert "frame over" in chan.last_drop


def test_a_page_that_stops_answering_pings_is_quiet(channel):
    chan, listener, url = channel

    async def stall():
        async with connect(url) as ws:
            await ws.send(json.dumps({"type": "key", "key": "w", "down": True}))
            await asyncio.sleep(0.1)
            time.sleep(QUIET_S + 1.0)  # this loop answers no ping meanwhile, as over a stalled network
            await asyncio.sleep(0.5)

    asyncio.run(stall())
    assert wait_until(lambda: ("closed", 1) in listener.events, 30.0)
    assert ("quiet", 1) in listener.events
    assert listener.events.index(("quiet", 1)) < listener.events.index(("closed", 1))
