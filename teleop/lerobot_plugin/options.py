"""Checks of the plugin's options that need neither LeRobot nor MuJoCo (one-line ValueErrors at parse time)."""

from __future__ import annotations

import math
import re

ACTION_SPACES = ("joint", "ee_delta")
OBS_TYPES = ("state", "pixels_agent_pos")
RECORD_FORMATS = ("mcap", "hdf5")
_SIZE = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


def parse_image_size(text: str) -> tuple[int, int]:
    """'96x96' -> (width, height) in pixels, 1 to 4096 each."""
    match = _SIZE.match(str(text))
    size = (int(match[1]), int(match[2])) if match else (0, 0)
    if not all(0 < v <= 4096 for v in size):
        raise ValueError(f"image_size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 96x96")
    return size


def parse_camera_list(text: str | None) -> list[str]:
    """'front,wrist' -> ['front', 'wrist']; '' or 'none' -> []."""
    names = [c.strip() for c in (text or "").split(",") if c.strip()]
    return [] if names == ["none"] else names


def check_choice(what: str, value: str, choices: tuple[str, ...]) -> None:
    if value not in choices:
        raise ValueError(f"{what} {value!r}: choose one of {', '.join(choices)}")


def check_rate(what: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and 0 < value <= 1000):
        raise ValueError(f"{what} must be a rate in Hz, more than 0 and at most 1000 (got {value!r})")


def check_seed(value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(f"seed must be a whole number >= 0 (got {value!r})")
