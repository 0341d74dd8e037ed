"""Checks of configuration values shared by the sampling configs (errors name the field)."""

from __future__ import annotations

import math


def is_finite_number(value: object) -> bool:
    """Whether ``value`` is a finite int or float (not a bool)."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def check_positive_range(value: object, owner: str, name: str, allow_none: bool = False) -> None:
    """Check a ``(low, high)`` tuple of finite numbers with ``0 < low <= high``.

    Raises:
        ValueError: Naming ``owner`` and the field ``name``.
    """
    if allow_none and value is None:
        return
    ok = (
        isinstance(value, tuple)
        and len(value) == 2
        and all(is_finite_number(v) for v in value)
        and 0.0 < value[0] <= value[1]
    )
    if not ok:
        kind = "None or a tuple" if allow_none else "a tuple"
        raise ValueError(
            f"{owner}: '{name}' must be {kind} (low, high) of finite numbers with "
            f"0 < low <= high, got {value!r}"
        )
