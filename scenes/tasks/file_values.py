"""A task file's values as written: lengths (m) in the file's units, numbers, [low, high] ranges.

A length is a number (times the file's scale) or "K unit" with unit size|spread|reach|m,
the layout lengths of the robot the task is built for. Every bad value raises
TaskFileError with one line naming the file and the field.
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from typing import Any

from scenes.assembly.robot import SceneError
from scenes.tasks.geometry import Units

LENGTH = re.compile(r"\s*([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*(size|spread|reach|m)\s*")


class TaskFileError(SceneError):
    """A task file that cannot be used; the message is one line naming the file and the field."""


def length(value: Any, units: Units, where: str) -> float:
    """A length (m): a number (times the file's scale) or "K unit" with unit size|spread|reach|m."""
    if isinstance(value, bool):
        raise TaskFileError(f"{where}: expected a length, got {value!r}")
    if isinstance(value, (int, float)):
        return float(value) * units.scale
    if isinstance(value, str):
        m = LENGTH.fullmatch(value)
        if m:
            k, unit = float(m.group(1)), m.group(2)
            return k if unit == "m" else k * {"size": units.size, "spread": units.spread, "reach": units.reach}[unit]
    raise TaskFileError(f"{where}: expected a length (a number, or \"K size|spread|reach|m\"), got {value!r}")


def lengths(value: Any, n: int | tuple[int, ...], units: Units, where: str) -> list[float]:
    """`n` lengths (m) from a list (or one value when n is 1)."""
    counts = (n,) if isinstance(n, int) else n
    if not isinstance(value, list):
        value = [value]
    if len(value) not in counts:
        raise TaskFileError(f"{where}: expected {' or '.join(map(str, counts))} value(s), got {len(value)}")
    return [length(v, units, where) for v in value]


def positive_lengths(value: Any, n: int | tuple[int, ...], where: str) -> None:
    """Check `n` lengths as written, before any layout: each a number or "K unit", every one > 0.

    Units are positive lengths, so the sign of the written number is the sign of the length.
    """
    counts = (n,) if isinstance(n, int) else n
    values = value if isinstance(value, list) else [value]
    if len(values) not in counts:
        raise TaskFileError(f"{where}: expected {' or '.join(map(str, counts))} value(s), got {len(values)}")
    for v in values:
        m = LENGTH.fullmatch(v) if isinstance(v, str) else None
        if isinstance(v, bool) or not (isinstance(v, (int, float)) or m):
            raise TaskFileError(f"{where}: expected a length (a number, or \"K size|spread|reach|m\"), got {v!r}")
        if (float(m.group(1)) if m else v) <= 0:
            raise TaskFileError(f"{where}: every size must be > 0, got {value!r}")


def numbers(value: Any, n: int | tuple[int, ...], where: str) -> list[float]:
    """`n` plain numbers (no units) from a list (or one value when n is 1)."""
    counts = (n,) if isinstance(n, int) else n
    if not isinstance(value, list):
        value = [value]
    if len(value) not in counts or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
        raise TaskFileError(f"{where}: expected {' or '.join(map(str, counts))} number(s), got {value!r}")
    return [float(v) for v in value]


def length_range(value: Any, units: Units | None, where: str) -> tuple[float, float]:
    """[lo, hi] (or a single value) as lengths, or as plain numbers when units is None."""
    if not isinstance(value, list):
        value = [value]
    if len(value) not in (1, 2):
        raise TaskFileError(f"{where}: expected [low, high] or one value, got {value!r}")
    vals = [length(v, units, where) if units is not None else numbers(v, 1, where)[0] for v in value]
    lo, hi = vals[0], vals[-1]
    if hi < lo:
        raise TaskFileError(f"{where}: low {lo:g} is above high {hi:g}")
    return lo, hi


def required_str(raw: Mapping[str, Any], key: str, where: str) -> str:
    """`raw[key]` as a non-empty string."""
    value = raw.get(key)
    if not isinstance(value, str) or not value.strip():
        raise TaskFileError(f"{where}: {key}: missing (a non-empty string)")
    return value
