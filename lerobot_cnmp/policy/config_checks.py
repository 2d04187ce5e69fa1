"""The value checks the config sections share: a clear ``ValueError`` naming the setting."""

from __future__ import annotations

import math
import numbers


def check(ok: bool, message: str) -> None:
    if not ok:
        raise ValueError(message)


def is_count(x, low: int = 0) -> bool:
    """An integer >= low (bools, NaN and inf are not)."""
    return not isinstance(x, bool) and isinstance(x, numbers.Real) and math.isfinite(x) and x == int(x) and x >= low
