"""What a page may say on the input channel, checked before anything acts on it.

A page is code the server does not control (a stale tab, another script, a
hostile one holding the token), so every message is parsed here, in the
server's network thread, into one of a few small frozen types, or rejected
with a one-line reason. Nothing downstream (the key state, the control loop)
ever sees a message that is not one of these.

Messages are JSON objects of at most MAX_BYTES, text frames on the channel's websocket at PATH
(plain Python here, so the campaign lobby, a stdlib server, hands out the channel's URL without
loading viser), with exactly the fields of their type:
  {"type": "hello", "client": 3, "agent": "Mozilla/5.0 ..."}   who this page is
  {"type": "view", "client": 3, "software_gl": true}            its WebGL draws in software (no GPU)
  {"type": "key", "key": "w", "down": true}                    a bound key, as KeyboardEvent.key
  {"type": "release_all", "why": "blur"}                       the page lost focus or is going
  {"type": "gamepad", "id": "Xbox ...", "axes": [..], "buttons": [..], "connected": true}
                                                  a pad's state (standard mapping), <= 8 axes, <= 20 buttons
  {"type": "phone", "quat": [w, x, y, z], "pos": [x, y, z] | null, "clutch": true}
                                                  the phone page's pose (devices/phone.py's frames)
  {"type": "phone_button", "action": "gripper"}   a phone page button: gripper or an episode event
  {"type": "hid", "report_id": 1, "data": [..]}   one WebHID input report (<= 63 bytes after the id)
  {"type": "hid_connect", "product": "SpaceMouse Compact"} / {"type": "hid_disconnect"}
Keys are named as the browser names them (`KeyboardEvent.key`) and mapped to
the keyboard device's bindings here, so the page and the server keyboard
share one table (devices.keyboard.BINDINGS).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

from devices.keyboard import ALIASES, KEY_ACTION

PATH = "/teleop/input"  # the channel's websocket, beside viser's on the same port (input_channel)
MAX_BYTES = 512  # the longest valid message is a hello with its agent string
MAX_AGENT = 200
MAX_CLIENT_ID = 2**31 - 1
REASONS = ("blur", "hidden", "pagehide", "disconnect", "reset")
# KeyboardEvent.key values of the named keys in the bindings; other bindings are single characters.
BROWSER_NAMES: dict[str, str] = {" ": "space", "Enter": "enter", "Backspace": "backspace", "Tab": "tab"}


class Rejected(ValueError):
    """A message that is dropped; the text says why in one line."""


@dataclass(frozen=True)
class Hello:
    client: int | None  # viser's client id of the page, for naming it on the panel
    agent: str


@dataclass(frozen=True)
class View:
    client: int | None  # viser's client id of the page
    software_gl: bool  # WebGL drawn by a CPU renderer (SwiftShader, llvmpipe): teleop/web/shared/view_quality.py


@dataclass(frozen=True)
class Key:
    name: str  # the binding's key name (devices.keyboard.KEY_ACTION), not the browser's
    down: bool


@dataclass(frozen=True)
class ReleaseAll:
    why: str


@dataclass(frozen=True)
class Gamepad:
    pad_id: str
    axes: tuple[float, ...]  # each in [-1, 1]
    buttons: tuple[float, ...]  # each in [0, 1]
    connected: bool


@dataclass(frozen=True)
class Phone:
    quat: tuple[float, float, float, float]  # phone -> earth, wxyz, unit length within 1e-3
    pos: tuple[float, float, float] | None  # m (WebXR), |each| <= 100
    clutch: bool


@dataclass(frozen=True)
class PhoneButton:
    action: str  # "gripper" or one of PHONE_EVENTS


@dataclass(frozen=True)
class Hid:
    report_id: int
    data: bytes


@dataclass(frozen=True)
class HidConnect:
    product: str


@dataclass(frozen=True)
class HidDisconnect:
    pass


InputMessage = Hello | View | Key | ReleaseAll | Gamepad | Phone | PhoneButton | Hid | HidConnect | HidDisconnect
FIELDS: dict[str, frozenset[str]] = {
    "hello": frozenset({"type", "client", "agent"}),
    "view": frozenset({"type", "client", "software_gl"}),
    "key": frozenset({"type", "key", "down"}),
    "release_all": frozenset({"type", "why"}),
    "gamepad": frozenset({"type", "id", "axes", "buttons", "connected"}),
    "phone": frozenset({"type", "quat", "pos", "clutch"}),
    "phone_button": frozenset({"type", "action"}),
    "hid": frozenset({"type", "report_id", "data"}),
    "hid_connect": frozenset({"type", "product"}),
    "hid_disconnect": frozenset({"type"}),
}
MAX_AXES, MAX_BUTTONS, MAX_HID_BYTES, MAX_PRODUCT = 8, 20, 63, 80
PHONE_ACTIONS = ("gripper", "record", "start", "save", "discard", "reset")


def _numbers(value, count: int | tuple[int, int], low: float, high: float, what: str) -> tuple[float, ...]:
    """A list of finite JSON numbers (not booleans) of `count` entries (or a (min, max) range), each in [low, high]."""
    least, most = (count, count) if isinstance(count, int) else count
    if not isinstance(value, list) or not least <= len(value) <= most:
        raise Rejected(f"{what}: expected a list of {least if least == most else f'{least} to {most}'} numbers")
    if not all(type(v) in (int, float) and math.isfinite(v) and low <= v <= high for v in value):
        raise Rejected(f"{what}: every entry must be a number from {low:g} to {high:g}")
    return tuple(float(v) for v in value)


def _device_message(kind: str, data: dict) -> InputMessage:
    """The browser devices' messages (gamepad, phone, WebHID), checked field by field."""
    if kind == "gamepad":
        if not isinstance(data["id"], str) or len(data["id"]) > 120 or not isinstance(data["connected"], bool):
            raise Rejected("gamepad: 'id' must be a string of at most 120 characters and 'connected' true or false")
        axes = _numbers(data["axes"], (0, MAX_AXES), -1.0, 1.0, "gamepad axes")
        buttons = _numbers(data["buttons"], (0, MAX_BUTTONS), 0.0, 1.0, "gamepad buttons")
        return Gamepad(data["id"], axes, buttons, data["connected"])
    if kind == "phone":
        quat = _numbers(data["quat"], 4, -1.0, 1.0, "phone quat")
        if abs(math.hypot(*quat) - 1.0) > 1e-3:
            raise Rejected("phone quat: not a unit quaternion")
        pos = None if data["pos"] is None else _numbers(data["pos"], 3, -100.0, 100.0, "phone pos")
        if not isinstance(data["clutch"], bool):
            raise Rejected("phone: 'clutch' must be true or false")
        return Phone(quat, pos, data["clutch"])  # type: ignore[arg-type]
    if kind == "phone_button":
        if data["action"] not in PHONE_ACTIONS:
            raise Rejected(f"phone_button: 'action' must be one of {', '.join(PHONE_ACTIONS)}")
        return PhoneButton(data["action"])
    if kind == "hid":
        report_id, raw = data["report_id"], data["data"]
        if type(report_id) is not int or not 0 <= report_id <= 255:
            raise Rejected("hid: 'report_id' must be a whole number from 0 to 255")
        if not isinstance(raw, list) or len(raw) > MAX_HID_BYTES or not all(type(b) is int and 0 <= b <= 255 for b in raw):
            raise Rejected(f"hid: 'data' must be a list of at most {MAX_HID_BYTES} bytes (0-255)")
        return Hid(report_id, bytes(raw))
    if kind == "hid_connect":
        if not isinstance(data["product"], str) or len(data["product"]) > MAX_PRODUCT:
            raise Rejected(f"hid_connect: 'product' must be a string of at most {MAX_PRODUCT} characters")
        return HidConnect(data["product"])
    return HidDisconnect()


def binding_name(browser_key: str) -> str | None:
    """KeyboardEvent.key -> the keyboard binding's key name ("w", "space", "="), None if unbound."""
    name = BROWSER_NAMES.get(browser_key)
    if name is None and len(browser_key) == 1:
        name = browser_key.lower()
    name = ALIASES.get(name, name) if name is not None else None
    return name if name in KEY_ACTION else None


def browser_keys() -> list[str]:
    """Every KeyboardEvent.key the page should catch and send (both cases of letters)."""
    named = {v: k for k, v in BROWSER_NAMES.items()}
    keys: set[str] = set()
    for name in KEY_ACTION:
        key = named.get(name, name)
        keys.update({key, key.upper()} if len(key) == 1 else {key})
    keys.update(alias for alias, target in ALIASES.items() if target in KEY_ACTION)
    return sorted(k for k in keys if binding_name(k) is not None)


def _no_constant(word: str):
    raise Rejected(f"{word} is not a number JSON allows")


def decode_frame(raw: str | bytes, max_bytes: int = MAX_BYTES) -> object:
    """A page's websocket frame as JSON (text, at most `max_bytes`, no NaN or Infinity), or Rejected: the first
    check of every page channel's messages (this one's and the XR page's)."""
    if not isinstance(raw, str):
        raise Rejected("binary frame (messages are JSON text)")
    if len(raw.encode("utf-8", "replace")) > max_bytes:
        raise Rejected(f"message longer than {max_bytes} bytes")
    try:
        return json.loads(raw, parse_constant=_no_constant)
    except (json.JSONDecodeError, RecursionError) as exc:
        raise Rejected(f"not JSON ({exc.__class__.__name__})") from None


def parse(raw: str | bytes) -> InputMessage:
    """One message from a page, or Rejected naming what is wrong with it."""
    data = decode_frame(raw)
    if not isinstance(data, dict):
        raise Rejected("not a JSON object")
    kind = data.get("type")
    if not isinstance(kind, str) or kind not in FIELDS:
        raise Rejected(f"unknown type {str(kind)[:20]!r}")
    extra = set(data) - FIELDS[kind]
    missing = FIELDS[kind] - set(data) - ({"client"} if kind in ("hello", "view") else set())
    if extra or missing:
        raise Rejected(f"{kind}: " + ", ".join([*(f"unknown field {f[:20]!r}" for f in sorted(extra)),
                                                 *(f"missing {f!r}" for f in sorted(missing))]))
    if kind in ("gamepad", "phone", "phone_button", "hid", "hid_connect", "hid_disconnect"):
        return _device_message(kind, data)
    if kind == "key":
        key, down = data["key"], data["down"]
        if not isinstance(key, str) or not isinstance(down, bool):
            raise Rejected("key: 'key' must be a string and 'down' true or false")
        name = binding_name(key)
        if name is None:
            raise Rejected(f"key: {key[:20]!r} is not bound")
        return Key(name, down)
    if kind in ("hello", "view"):
        client = data.get("client")
        if client is not None and (type(client) is not int or not 0 <= client <= MAX_CLIENT_ID):
            raise Rejected(f"{kind}: 'client' must be a whole number from 0 or null")
    if kind == "view":
        if not isinstance(data["software_gl"], bool):
            raise Rejected("view: 'software_gl' must be true or false")
        return View(client, data["software_gl"])
    if kind == "hello":
        agent = data["agent"]
        if not isinstance(agent, str) or len(agent) > MAX_AGENT:
            raise Rejected(f"hello: 'agent' must be a string of at most {MAX_AGENT} characters")
        return Hello(client, agent)
    why = data["why"]  # release_all
    if not isinstance(why, str) or why not in REASONS:
        raise Rejected(f"release_all: 'why' must be one of {', '.join(REASONS)}")
    return ReleaseAll(why)
