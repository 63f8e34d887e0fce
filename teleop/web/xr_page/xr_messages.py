"""What the XR page may say on its websocket (`/teleop/xr`), checked before anything acts on it.

JSON text frames of at most MAX_BYTES, exactly these fields:
  {"type": "xr_pose", "hand": "left" | "right", "frame": 12, "t": 1764345600123.4, "tracked": true,
   "pos": [x, y, z] | null, "quat": [w, x, y, z] | null, "clutch": true, "opening": 0.0..1.0 | null, "mode": "controller" | "hand"}
      one controller's (or tracked hand's) pose in the world frame (MuJoCo's: z up, m; the page maps
      WebXR's local-floor frame through its placement), the clutch (squeeze, or the hand's pinch)
      and the gripper's opening (1 - trigger; a hand's thumb-index gap with hysteresis); `t`: when the XR frame
      that saw it began (ms since the epoch, the page's clock: the frame-to-tick latency, on one machine)
  {"type": "xr_button", "hand": "left" | "right", "button": "a" | "b" | "x" | "y"}   a press
  {"type": "xr_release", "why": "blurred" | "hidden" | "ended" | "pagehide"}   let go of every arm
  {"type": "xr_config", "scale": 1.0}                       robot metres per metre the hand moves
A pose's numbers are not checked here beyond being numbers or null: a NaN (sent by JSON as null)
or an absurd pose is the device's to drop and count (teleop/web/xr_page/xr_device.py), so that
the count says how often the headset sent one.
"""

from __future__ import annotations

from dataclasses import dataclass

from teleop.web.shared.input_messages import Rejected, decode_frame

MAX_BYTES = 512
HANDS = ("left", "right")
BUTTONS = ("a", "b", "x", "y")
RELEASES = ("blurred", "hidden", "ended", "pagehide")
MODES = ("controller", "hand")
SCALE_RANGE = (0.1, 5.0)




@dataclass(frozen=True)
class XrPose:
    hand: str
    frame: int  # the page's XR frame counter (echoed back in the poses message: latency)
    t_ms: float  # the XR frame's start, ms since the epoch (page clock)
    tracked: bool
    pos: tuple[float | None, ...] | None  # m, world; None entries: a NaN the page could not send
    quat: tuple[float | None, ...] | None  # wxyz, world
    clutch: bool
    opening: float | None  # 0 closed .. 1 open
    mode: str


@dataclass(frozen=True)
class XrButton:
    hand: str
    button: str


@dataclass(frozen=True)
class XrRelease:
    why: str


@dataclass(frozen=True)
class XrConfig:
    scale: float


XrMessage = XrPose | XrButton | XrRelease | XrConfig
FIELDS = {
    "xr_pose": frozenset({"type", "hand", "frame", "t", "tracked", "pos", "quat", "clutch", "opening", "mode"}),
    "xr_button": frozenset({"type", "hand", "button"}),
    "xr_release": frozenset({"type", "why"}),
    "xr_config": frozenset({"type", "scale"}),
}


def _number(value) -> bool:
    return type(value) in (int, float)


def _vector(value, count: int, what: str) -> tuple[float | None, ...] | None:
    if value is None:
        return None
    if not isinstance(value, list) or len(value) != count or not all(v is None or _number(v) for v in value):
        raise Rejected(f"xr_pose: '{what}' must be null or a list of {count} numbers")
    return tuple(None if v is None else float(v) for v in value)


def parse(raw: str | bytes) -> XrMessage:
    """One message from the XR page, or Rejected naming what is wrong with it."""
    data = decode_frame(raw, MAX_BYTES)
    if not isinstance(data, dict) or data.get("type") not in FIELDS:
        raise Rejected("unknown message type")
    kind = data["type"]
    if set(data) != FIELDS[kind]:
        raise Rejected(f"{kind}: fields must be exactly {', '.join(sorted(FIELDS[kind]))}")
    if kind == "xr_pose":
        if data["hand"] not in HANDS or data["mode"] not in MODES:
            raise Rejected("xr_pose: 'hand' must be left or right and 'mode' controller or hand")
        if type(data["frame"]) is not int or not isinstance(data["tracked"], bool) or not isinstance(data["clutch"], bool):
            raise Rejected("xr_pose: 'frame' must be a whole number, 'tracked' and 'clutch' true or false")
        if not _number(data["t"]) or not 0 <= data["t"] < 1e14:
            raise Rejected("xr_pose: 't' must be a time in ms since the epoch")
        opening = data["opening"]
        if opening is not None and not (_number(opening) and 0.0 <= opening <= 1.0):
            raise Rejected("xr_pose: 'opening' must be null or a number from 0 to 1")
        return XrPose(data["hand"], data["frame"], float(data["t"]), data["tracked"], _vector(data["pos"], 3, "pos"),
                      _vector(data["quat"], 4, "quat"), data["clutch"], None if opening is None else float(opening), data["mode"])
    if kind == "xr_button":
        if data["hand"] not in HANDS or data["button"] not in BUTTONS:
            raise Rejected("xr_button: 'hand' must be left or right and 'button' one of a, b, x, y")
        return XrButton(data["hand"], data["button"])
    if kind == "xr_release":
        if data["why"] not in RELEASES:
            raise Rejected(f"xr_release: 'why' must be one of {', '.join(RELEASES)}")
        return XrRelease(data["why"])
    scale = data["scale"]
    if not _number(scale) or not SCALE_RANGE[0] <= scale <= SCALE_RANGE[1]:
        raise Rejected(f"xr_config: 'scale' must be a number from {SCALE_RANGE[0]:g} to {SCALE_RANGE[1]:g}")
    return XrConfig(float(scale))
