"""Checks of configuration fields: the one way a configuration dataclass validates itself.

Each ``check_*`` function checks one field and raises :class:`~svr.errors.ConfigFieldError`
naming the configuration class (``owner``), the field, what the field accepts and the value given,
so that a caller (the command line) can name its own option instead of the field. A config's
``__post_init__`` is a short list of these checks, then its cross-field invariants (raised as
:class:`~svr.errors.ConfigFieldError` naming the main field)::

    def __post_init__(self) -> None:
        owner = "RegistrationConfig"
        check_int(owner, "levels", self.levels, minimum=1)
        check_int(owner, "iterations", self.iterations, minimum=0)
        check_number(owner, "damping", self.damping, gt=0)

Conventions:

* An integer is an ``int`` that is not a ``bool``.
* A number is a finite ``int`` or ``float`` (``float`` subclasses such as ``numpy.float64``
  included) that is not a ``bool``: NaN and infinities are refused.
* A sequence field takes a tuple; with ``allow_list=True`` also a list (a configuration read
  from JSON), which its check returns as a tuple for the config to store
  (``object.__setattr__`` in a frozen dataclass), so that a config holds tuples.
* ``allow_none=True`` also accepts ``None`` (the field's "not set").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any, Literal, TypeGuard, overload

from svr.errors import ConfigFieldError

__all__ = [
    "check_bool",
    "check_callable",
    "check_choice",
    "check_fraction",
    "check_instance",
    "check_instance_tuple",
    "check_int",
    "check_int_tuple",
    "check_number",
    "check_number_tuple",
    "check_range",
    "check_str",
    "is_finite_number",
    "is_integer",
]


def is_integer(value: object) -> TypeGuard[int]:
    """Whether ``value`` is an ``int`` that is not a ``bool``."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_finite_number(value: object) -> TypeGuard[float]:
    """Whether ``value`` is a finite ``int`` or ``float`` that is not a ``bool``."""
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _text(bound: float) -> str:
    """A bound as written in a message: ``1``, ``0.5``, ``1e-06``."""
    return str(bound) if isinstance(bound, int) else f"{bound:g}"


def _bounds(gt: float | None, ge: float | None, lt: float | None, le: float | None) -> str:
    """The bounds in words: ``"in [0, 1)"`` for both ends, ``">= 0"`` for one, ``""`` for none.

    Raises:
        TypeError: If both bounds of one end are given (a programming error).
    """
    if (gt is not None and ge is not None) or (lt is not None and le is not None):
        raise TypeError("give at most one lower bound (gt, ge) and one upper bound (lt, le)")
    low = f"({_text(gt)}" if gt is not None else f"[{_text(ge)}" if ge is not None else ""
    high = f"{_text(lt)})" if lt is not None else f"{_text(le)}]" if le is not None else ""
    if low and high:
        return f"in {low}, {high}"
    comparisons = [(">", gt), (">=", ge), ("<", lt), ("<=", le)]
    return next((f"{sign} {_text(bound)}" for sign, bound in comparisons if bound is not None), "")


def _kind(kind: str, bounds: str) -> str:
    """``"a finite number > 0"``, ``"an integer"``; an interval alone (``"in [0, 1]"``)."""
    return f"{kind} {bounds}".rstrip() if not bounds.startswith("in ") else bounds


def _within(
    value: float, gt: float | None, ge: float | None, lt: float | None, le: float | None
) -> bool:
    return (
        (gt is None or value > gt)
        and (ge is None or value >= ge)
        and (lt is None or value < lt)
        and (le is None or value <= le)
    )


def _or_none(expected: str, allow_none: bool) -> str:
    return f"None or {expected}" if allow_none else expected


def check_int(
    owner: str,
    name: str,
    value: object,
    minimum: int | None = None,
    maximum: int | None = None,
    allow_none: bool = False,
) -> None:
    """Check an integer field (a ``bool`` is refused).

    Args:
        owner: The configuration class, e.g. ``"TrainConfig"``.
        name: The field.
        value: Its value.
        minimum: The smallest value accepted, if any.
        maximum: The largest value accepted, if any.
        allow_none: Also accept ``None``.

    Raises:
        ConfigFieldError: Expecting e.g. ``"an integer >= 1"`` or ``"an integer in [1, 8]"``.
    """
    if allow_none and value is None:
        return
    if is_integer(value) and _within(value, None, minimum, None, maximum):
        return
    expected = f"an integer {_bounds(None, minimum, None, maximum)}".rstrip()
    raise ConfigFieldError(owner, name, _or_none(expected, allow_none), value)


def check_number(
    owner: str,
    name: str,
    value: object,
    *,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    allow_none: bool = False,
) -> None:
    """Check a finite number field, with optional open (``gt``, ``lt``) or closed bounds.

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value: a finite ``int`` or ``float``, not a ``bool``.
        gt: Exclusive lower bound.
        ge: Inclusive lower bound.
        lt: Exclusive upper bound.
        le: Inclusive upper bound.
        allow_none: Also accept ``None``.

    Raises:
        ConfigFieldError: Expecting e.g. ``"a finite number > 0"`` (one bound) or ``"in [0, 1)"``
            (both).
        TypeError: If both bounds of one end are given (a programming error).
    """
    expected = _kind("a finite number", _bounds(gt, ge, lt, le))
    if allow_none and value is None:
        return
    if is_finite_number(value) and _within(value, gt, ge, lt, le):
        return
    raise ConfigFieldError(owner, name, _or_none(expected, allow_none), value)


def check_fraction(
    owner: str,
    name: str,
    value: object,
    *,
    include_zero: bool = True,
    include_one: bool = True,
    allow_none: bool = False,
) -> None:
    """Check a fraction or a probability: a number in ``[0, 1]``, or with an open end.

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value.
        include_zero: Accept 0.
        include_one: Accept 1.
        allow_none: Also accept ``None``.

    Raises:
        ConfigFieldError: Expecting e.g. ``"in [0, 1]"`` or ``"in (0, 1)"``.
    """
    check_number(
        owner,
        name,
        value,
        ge=0 if include_zero else None,
        gt=None if include_zero else 0,
        le=1 if include_one else None,
        lt=None if include_one else 1,
        allow_none=allow_none,
    )


def check_bool(owner: str, name: str, value: object) -> None:
    """Check a flag: ``True`` or ``False`` (not ``0``, ``1`` or ``None``).

    Raises:
        ConfigFieldError: Expecting ``"a bool"``.
    """
    if not isinstance(value, bool):
        raise ConfigFieldError(owner, name, "a bool", value)


def check_str(owner: str, name: str, value: object, allow_none: bool = False) -> None:
    """Check a free-text field (a device, a path): a non-empty string.

    Raises:
        ConfigFieldError: Expecting ``"a non-empty string"``.
    """
    if allow_none and value is None:
        return
    if not (isinstance(value, str) and value):
        raise ConfigFieldError(owner, name, _or_none("a non-empty string", allow_none), value)


def check_choice(owner: str, name: str, value: object, choices: Sequence[object]) -> None:
    """Check a field that takes one of a few values (a name, a mode).

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value; it must be of a choice's type (``1`` is not ``"1"``).
        choices: The values accepted, in the order the message lists them.

    Raises:
        ConfigFieldError: Expecting e.g. ``"one of 'adamw', 'sgd'"``.
    """
    if not any(isinstance(value, type(choice)) and value == choice for choice in choices):
        listed = ", ".join(repr(choice) for choice in choices)
        raise ConfigFieldError(owner, name, f"one of {listed}", value)


def check_instance(
    owner: str, name: str, value: object, cls: type, allow_none: bool = False
) -> None:
    """Check a field that holds an object of a class (a nested configuration).

    Raises:
        ConfigFieldError: Expecting e.g. ``"a SliceConfig"``.
    """
    if allow_none and value is None:
        return
    if not isinstance(value, cls):
        raise ConfigFieldError(owner, name, _or_none(f"a {cls.__name__}", allow_none), value)


def check_callable(owner: str, name: str, value: object) -> None:
    """Check a field that holds a function.

    Raises:
        ConfigFieldError: Expecting ``"callable"``.
    """
    if not callable(value):
        raise ConfigFieldError(owner, name, "callable", value)


def _as_tuple(
    value: object,
    length: int | Sequence[int] | None,
    allow_empty: bool,
    allow_list: bool,
    item_ok: Callable[[Any], bool],
) -> tuple | None:
    """``value`` as a tuple if it is a tuple (or list) of an accepted length whose items pass."""
    if not isinstance(value, tuple | list if allow_list else tuple):
        return None
    items = tuple(value)
    lengths = None if length is None else [length] if isinstance(length, int) else list(length)
    if lengths is not None and len(items) not in lengths:
        return None
    if not (allow_empty or items) or not all(item_ok(item) for item in items):
        return None
    return items


def _tuple_text(length: int | Sequence[int] | None, allow_empty: bool, items: str) -> str:
    """``"a tuple of 2 integers >= 1"``, ``"a non-empty tuple of finite numbers"``."""
    if length is None:
        return f"{'a' if allow_empty else 'a non-empty'} tuple of {items}"
    counts = [length] if isinstance(length, int) else list(length)
    return f"a tuple of {' or '.join(str(n) for n in counts)} {items}"


@overload
def check_int_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    minimum: int | None = None,
    maximum: int | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: Literal[False] = False,
) -> tuple[int, ...]: ...


@overload
def check_int_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    minimum: int | None = None,
    maximum: int | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: bool,
) -> tuple[int, ...] | None: ...


def check_int_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    minimum: int | None = None,
    maximum: int | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: bool = False,
) -> tuple[int, ...] | None:
    """Check a tuple of integers, e.g. a size ``(H, W)``.

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value.
        length: The number of items (or the numbers accepted), if fixed.
        minimum: The smallest item accepted, if any.
        maximum: The largest item accepted, if any.
        allow_empty: Accept an empty tuple (when ``length`` is not given).
        allow_list: Also accept a list (returned as a tuple).
        allow_none: Also accept ``None``.

    Returns:
        ``value`` as a tuple (``None`` for ``None``).

    Raises:
        ConfigFieldError: Expecting e.g. ``"a tuple of 2 integers >= 1"``.
    """
    if allow_none and value is None:
        return None
    items = _as_tuple(
        value,
        length,
        allow_empty,
        allow_list,
        lambda item: is_integer(item) and _within(item, None, minimum, None, maximum),
    )
    if items is None:
        bounds = _bounds(None, minimum, None, maximum)
        expected = _tuple_text(length, allow_empty, f"integers {bounds}".rstrip())
        raise ConfigFieldError(owner, name, _or_none(expected, allow_none), value)
    return items


@overload
def check_number_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: Literal[False] = False,
) -> tuple[float, ...]: ...


@overload
def check_number_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: bool,
) -> tuple[float, ...] | None: ...


def check_number_tuple(
    owner: str,
    name: str,
    value: object,
    *,
    length: int | Sequence[int] | None = None,
    gt: float | None = None,
    ge: float | None = None,
    lt: float | None = None,
    le: float | None = None,
    allow_empty: bool = True,
    allow_list: bool = False,
    allow_none: bool = False,
) -> tuple[float, ...] | None:
    """Check a tuple of finite numbers, each within the bounds given.

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value.
        length: The number of items (or the numbers accepted), if fixed.
        gt: Exclusive lower bound of every item.
        ge: Inclusive lower bound of every item.
        lt: Exclusive upper bound of every item.
        le: Inclusive upper bound of every item.
        allow_empty: Accept an empty tuple (when ``length`` is not given).
        allow_list: Also accept a list (returned as a tuple).
        allow_none: Also accept ``None``.

    Returns:
        ``value`` as a tuple (``None`` for ``None``).

    Raises:
        ConfigFieldError: Expecting e.g. ``"a non-empty tuple of finite numbers >= 0"``.
        TypeError: If both bounds of one end are given (a programming error).
    """
    bounds = _bounds(gt, ge, lt, le)
    if allow_none and value is None:
        return None
    items = _as_tuple(
        value,
        length,
        allow_empty,
        allow_list,
        lambda item: is_finite_number(item) and _within(item, gt, ge, lt, le),
    )
    if items is None:
        expected = _tuple_text(length, allow_empty, f"finite numbers {bounds}".rstrip())
        raise ConfigFieldError(owner, name, _or_none(expected, allow_none), value)
    return items


def check_instance_tuple(
    owner: str, name: str, value: object, cls: type, allow_list: bool = False
) -> tuple:
    """Check a tuple whose items are objects of one class (e.g. ``str``).

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value.
        cls: The class of every item.
        allow_list: Also accept a list (returned as a tuple).

    Returns:
        ``value`` as a tuple.

    Raises:
        ConfigFieldError: Expecting e.g. ``"a tuple of str"``.
    """
    items = _as_tuple(value, None, True, allow_list, lambda item: isinstance(item, cls))
    if items is None:
        raise ConfigFieldError(owner, name, f"a tuple of {cls.__name__}", value)
    return items


@overload
def check_range(
    owner: str,
    name: str,
    value: object,
    *,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
    integer: bool = False,
    allow_list: bool = False,
    allow_none: Literal[False] = False,
) -> tuple[Any, Any]: ...


@overload
def check_range(
    owner: str,
    name: str,
    value: object,
    *,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
    integer: bool = False,
    allow_list: bool = False,
    allow_none: bool,
) -> tuple[Any, Any] | None: ...


def check_range(
    owner: str,
    name: str,
    value: object,
    *,
    gt: float | None = None,
    ge: float | None = None,
    le: float | None = None,
    integer: bool = False,
    allow_list: bool = False,
    allow_none: bool = False,
) -> tuple[Any, Any] | None:
    """Check a ``(low, high)`` range: two finite numbers (or integers) with ``low <= high``.

    Args:
        owner: The configuration class.
        name: The field.
        value: Its value, a tuple of two items.
        gt: Exclusive lower bound of ``low``.
        ge: Inclusive lower bound of ``low``.
        le: Inclusive upper bound of ``high``.
        integer: Both ends are integers (a ``bool`` is refused).
        allow_list: Also accept a list (returned as a tuple).
        allow_none: Also accept ``None`` (no range).

    Returns:
        ``value`` as a tuple (``None`` for ``None``).

    Raises:
        ConfigFieldError: Expecting e.g. ``"a tuple (low, high) of finite numbers with
            0 < low <= high"``.
        TypeError: If both ``gt`` and ``ge`` are given (a programming error).
    """
    if gt is not None and ge is not None:
        raise TypeError("give at most one lower bound (gt, ge)")
    if allow_none and value is None:
        return None
    items = _as_tuple(value, 2, True, allow_list, is_integer if integer else is_finite_number)
    if (
        items is not None
        and _within(items[0], gt, ge, None, None)
        and items[0] <= items[1]
        and (le is None or items[1] <= le)
    ):
        return items
    low = f"{_text(gt)} < " if gt is not None else f"{_text(ge)} <= " if ge is not None else ""
    high = f" <= {_text(le)}" if le is not None else ""
    kind = "integers" if integer else "finite numbers"
    expected = f"a tuple (low, high) of {kind} with {low}low <= high{high}"
    raise ConfigFieldError(owner, name, _or_none(expected, allow_none), value)
