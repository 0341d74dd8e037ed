"""Configuration fields that a command-line option sets, declared once on the dataclass field.

A field made with :func:`option` carries its option's name, help text and metavar in its
metadata; the command line builds its parser from them (:mod:`svr.cli.config_options`), reports
a bad value under the option's name, and the provenance of a run lists every option with its
value (:func:`option_values`). Adding a field with :func:`option` to a configuration adds the
option to every command that takes that configuration, with nothing else to write.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

__all__ = ["OptionSpec", "option", "option_fields", "option_values"]


@dataclass(frozen=True)
class OptionSpec:
    """How a configuration field appears on the command line.

    Attributes:
        flag: The long option, e.g. ``"--ncc-threshold"``. For a bool field whose default is
            ``True`` the flag turns it off (``"--no-robust"``); otherwise a bool flag turns it on.
        help: What the option does (the default is appended from the field's default, or
            ``default_text``).
        metavar: The value's placeholder in the help, e.g. ``"MM"``.
        default_text: Shown as the default instead of the field's own, for a default that
            depends on other options (e.g. ``"16; 24 with --registration cnn"``).
    """

    flag: str
    help: str
    metavar: str | None = None
    default_text: str | None = None


def option(
    default: Any,
    flag: str,
    help: str,
    *,
    metavar: str | None = None,
    default_text: str | None = None,
) -> Any:
    """A dataclass field with ``default`` that the command-line option ``flag`` sets.

    Args:
        default: The field's default value (immutable: tuples, not lists).
        flag: The long option (``"--name"``; ``"--no-name"`` for a bool that defaults to ``True``).
        help: What the option does.
        metavar: The value's placeholder in the help.
        default_text: The default as the help shows it, where it is not the field's own.

    Returns:
        A :func:`dataclasses.field` whose metadata holds the :class:`OptionSpec`.

    Raises:
        ValueError: If ``flag`` does not start with ``--``.
    """
    if not flag.startswith("--"):
        raise ValueError(f"option(): 'flag' must start with '--', got {flag!r}")
    spec = OptionSpec(flag, help, metavar, default_text)
    return dataclasses.field(default=default, metadata={"option": spec})


def option_fields(
    config_class: type, prefix: tuple[str, ...] = ()
) -> Iterator[tuple[tuple[str, ...], dataclasses.Field, OptionSpec]]:
    """Every field of a (nested) configuration dataclass that an option sets.

    Args:
        config_class: A dataclass type; fields whose default is a dataclass instance (a group)
            are walked into.
        prefix: The field path of ``config_class`` in its parent (for the recursion).

    Yields:
        ``(path, field, spec)``: the field's path from ``config_class`` (e.g.
        ``("outliers", "ncc_threshold")``), the field and its option.
    """
    for item in dataclasses.fields(config_class):
        spec = item.metadata.get("option")
        if spec is not None:
            yield (*prefix, item.name), item, spec
            continue
        group = _group_class(item)
        if group is not None:
            yield from option_fields(group, (*prefix, item.name))


def _group_class(item: dataclasses.Field) -> type | None:
    """The dataclass type of a field that holds a group of settings, else ``None``."""
    if item.default_factory is not dataclasses.MISSING:
        value = item.default_factory()
        return type(value) if dataclasses.is_dataclass(value) else None
    return None


def option_values(config: Any) -> dict[str, Any]:
    """``{flag: value}`` of every option-backed field of a configuration, for provenance.

    Args:
        config: A configuration dataclass instance (groups included).

    Returns:
        The flag of each field made with :func:`option` and the field's value in ``config``
        (tuples as lists, for JSON); a flag that turns a field off (a bool field whose default
        is ``True``, ``"--no-robust"``) is ``True`` where it was given: the field's negation, so
        a log never reads ``--no-robust: True`` for a run that used the outlier weights.
    """
    out: dict[str, Any] = {}
    for path, item, spec in option_fields(type(config)):
        value: Any = config
        for name in path:
            value = getattr(value, name)
        if isinstance(value, bool) and item.default is True:
            value = not value
        out[spec.flag] = list(value) if isinstance(value, tuple) else value
    return out
