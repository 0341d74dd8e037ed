"""Command-line options made from the configuration fields that declare them.

A configuration field made with :func:`svr.options.option` names its option, help and metavar;
:func:`add_config_options` adds one argparse option per such field (its type, ``nargs`` and
choices from the field's annotation), :func:`config_from_options` builds the configuration from
the parsed values over a base (the defaults of :meth:`ReconstructionConfig.preset`, for
example), and :func:`option_names` maps each field to its option so that a bad value is reported
under the option's name (:func:`svr.cli.common.option_errors`). Nothing here names a field: a new
field with an option appears on every command that takes its configuration.
"""

from __future__ import annotations

import argparse
import dataclasses
import types
import typing
from typing import Any, Literal, get_args, get_origin

from svr.options import OptionSpec, option_fields

__all__ = [
    "add_config_options",
    "config_from_options",
    "option_dest",
    "option_names",
    "set_option_default",
]


def option_dest(spec: OptionSpec) -> str:
    """The argparse attribute of an option: its flag without dashes, ``-`` as ``_``."""
    return spec.flag.removeprefix("--").replace("-", "_")


def _owner(config_class: type, path: tuple[str, ...]) -> type:
    """The dataclass that holds the field at ``path`` (its last name) below ``config_class``."""
    owner = config_class
    for name in path[:-1]:
        group = next(f for f in dataclasses.fields(owner) if f.name == name)
        factory: Any = group.default_factory
        owner = type(factory())
    return owner


def _hint(owner: type, name: str) -> Any:
    """The type of field ``name`` of ``owner``, its annotation evaluated where it was written."""
    import inspect
    import sys

    for klass in owner.__mro__:
        annotation = inspect.get_annotations(klass).get(name)
        if annotation is not None:
            if not isinstance(annotation, str):
                return annotation
            namespace = vars(sys.modules[klass.__module__])
            return eval(annotation, dict(namespace))  # the class's own annotation, from source
    raise KeyError(f"{owner.__name__} has no field {name!r}")


def _argument(hint: Any, spec: OptionSpec, default: Any) -> dict[str, Any]:
    """The argparse keywords of an option whose field has type ``hint`` and ``default``."""
    if get_origin(hint) in (typing.Union, types.UnionType):
        hint = next(arg for arg in get_args(hint) if arg is not type(None))
    if hint is bool:
        return {"action": "store_true", "default": None, "help": spec.help}
    kwargs: dict[str, Any] = {"default": None, "metavar": spec.metavar}
    if get_origin(hint) is Literal:
        kwargs["choices"] = get_args(hint)
        kwargs["metavar"] = spec.metavar or "{" + ",".join(map(str, get_args(hint))) + "}"
    elif get_origin(hint) is tuple:
        items = get_args(hint)
        kwargs["type"] = items[0]
        kwargs["nargs"] = "+" if items[-1] is Ellipsis else len(items)
    else:
        kwargs["type"] = hint
    shown = spec.default_text
    if shown is None and default is not None:
        shown = " ".join(map(str, default)) if isinstance(default, tuple) else str(default)
    kwargs["help"] = spec.help + ("" if shown is None else f" (default: {shown})")
    return kwargs


def add_config_options(
    parser: argparse.ArgumentParser,
    config_class: type,
    titles: dict[str, str],
    groups: dict[str, argparse._ArgumentGroup] | None = None,
) -> dict[str, argparse._ArgumentGroup]:
    """Add an option for every field of ``config_class`` (groups included) that declares one.

    Args:
        parser: The command's parser.
        config_class: The configuration dataclass.
        titles: Help-section title per group field of ``config_class`` (``""`` for the fields of
            ``config_class`` itself); options of a group without a title go to ``""``'s.
        groups: Sections already made, by title (created and returned where missing).

    Returns:
        The sections by title, for the command's own options of the same kind.
    """
    groups = {} if groups is None else groups
    for path, item, spec in option_fields(config_class):
        title = titles.get(path[0] if len(path) > 1 else "", titles.get("", "settings"))
        if title not in groups:
            groups[title] = parser.add_argument_group(title)
        hint = _hint(_owner(config_class, path), item.name)
        bool_default = item.default if item.default is not dataclasses.MISSING else None
        groups[title].add_argument(
            spec.flag, dest=option_dest(spec), **_argument(hint, spec, bool_default)
        )
    return groups


def config_from_options(args: argparse.Namespace, base: Any) -> Any:
    """``base`` with every option given on the command line (not ``None``) set.

    A bool option sets its field to the opposite of the field's default (``--no-robust`` turns
    ``robust`` off). Lists become tuples. The configurations check themselves, so a bad value
    raises :class:`~svr.errors.ConfigFieldError` naming the field
    (:func:`svr.cli.common.option_errors` names the option instead).

    Args:
        args: The parsed options.
        base: The configuration whose values stand where no option was given.

    Returns:
        A new configuration of ``base``'s type.
    """
    changes: dict[tuple[str, ...], Any] = {}
    for path, item, spec in option_fields(type(base)):
        value = getattr(args, option_dest(spec), None)
        if value is None:
            continue
        if isinstance(value, bool):
            value = not item.default if value else item.default
        changes[path] = tuple(value) if isinstance(value, list) else value
    return _replaced(base, (), changes)


def _replaced(config: Any, prefix: tuple[str, ...], changes: dict[tuple[str, ...], Any]) -> Any:
    """``config`` with the changes below ``prefix`` applied, groups rebuilt where they change."""
    own: dict[str, Any] = {}
    for item in dataclasses.fields(config):
        path = (*prefix, item.name)
        if path in changes:
            own[item.name] = changes[path]
        elif any(key[: len(path)] == path for key in changes):
            own[item.name] = _replaced(getattr(config, item.name), path, changes)
    return dataclasses.replace(config, **own) if own else config


def option_names(config_class: type) -> dict[str, str]:
    """``{"Owner.field": flag}`` of every option-backed field, for :func:`option_errors`."""
    return {
        f"{_owner(config_class, path).__name__}.{item.name}": spec.flag
        for path, item, spec in option_fields(config_class)
    }


def set_option_default(parser: argparse.ArgumentParser, flag: str, value: Any) -> None:
    """Give a generated option another default in one command (its help says so).

    Args:
        parser: The command's parser.
        flag: The option, e.g. ``"--iterations"``.
        value: Its default in this command.

    Raises:
        KeyError: If the parser has no such option.
    """
    action = next(a for a in parser._actions if flag in a.option_strings)
    action.default = value
    if action.help is not None:
        action.help = action.help.split(" (default: ")[0] + f" (default: {value})"
