"""Numbers read from what a person or a device gave: one reading, so every check after it is a plain comparison."""

from __future__ import annotations

import math


def number_or_nan(value: object) -> float:
    """`float(value)`, or NaN when it is not a number ("abc", None, a list): NaN fails every range check
    (`0 < x`, `math.isfinite`), so a caller tests the range once and names the value in one error."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        return math.nan
