"""svr.validation: the field checks, and every configuration of the package checks every field.

The walk imports every module of the installed ``svr`` package, collects its configuration
dataclasses (a name ending in ``Config``, or any dataclass with a ``__post_init__``) and, for each
field, builds bad values from the field's type annotation: each must raise a
:class:`~svr.errors.ConfigFieldError` whose ``field`` is that field, and values that may or may not
be in range (``-1``, ``0``, a reversed range) must, when refused, be refused the same way (never a
``TypeError``, a plain ``ValueError`` or an error naming another field).
"""

from __future__ import annotations

import dataclasses
import importlib
import math
import pickle
import pkgutil
import sys
import types
import typing
from collections.abc import Callable, Iterator

import pytest
from layout import subpackage_folders

import svr
from svr.cli.common import CliError, option_errors
from svr.errors import ConfigFieldError
from svr.validation import (
    check_bool,
    check_callable,
    check_choice,
    check_fraction,
    check_instance,
    check_instance_tuple,
    check_int,
    check_int_tuple,
    check_number,
    check_number_tuple,
    check_range,
    check_str,
    is_finite_number,
    is_integer,
)

_DATA_CONTAINERS = {
    "Image": "an image: its __post_init__ checks the tensors' shapes",
    "PoseTable": "a table of poses: tensor shapes (its 'frame' is checked by check_choice)",
    "SliceSet": "the slices of a reconstruction: tensor shapes (and 'frame', by check_choice)",
    "AugmentParams": "drawn augmentation parameters: tensor shapes",
}
"""Dataclasses whose ``__post_init__`` checks tensor shapes (svr.geometry._validation's concern,
no configuration values), with the reason; they are not walked."""

_ACCEPTS_ANY_STRING = {
    ("PoseRepresentation", "name"): "annotated with the registered names, but a new "
    "representation registers a new one (tests/test_registry.py does)",
}
"""Fields whose annotation is narrower than what they accept: checked as free strings."""

_NAN, _INF = math.nan, math.inf


# --- the walk ------------------------------------------------------------------------------------


def _walk(package: types.ModuleType, done: set[str]) -> None:
    done.add(package.__name__)
    for info in pkgutil.walk_packages(package.__path__, package.__name__ + "."):
        if info.name.rsplit(".", 1)[-1] == "__main__":  # runs the command line when imported
            continue
        importlib.import_module(info.name)


def _package_modules() -> list[types.ModuleType]:
    """Every module of the installed ``svr`` package.

    The editable install maps svr.models, svr.sampling, ... to folders beside svr/, outside
    ``svr.__path__``: each of pyproject's subpackages is walked, and every package imported
    meanwhile in turn.
    """
    done: set[str] = set()
    _walk(svr, done)
    for name in subpackage_folders():
        _walk(importlib.import_module(name), done)
    while True:
        packages = [
            module
            for name, module in list(sys.modules.items())
            if name.startswith("svr.") and hasattr(module, "__path__") and name not in done
        ]
        if not packages:
            break
        for package in packages:
            _walk(package, done)
    return [module for name, module in sorted(sys.modules.items()) if name.split(".")[0] == "svr"]


def _config_classes() -> dict[str, type]:
    found: dict[str, type] = {}
    for module in _package_modules():
        for obj in vars(module).values():
            if (
                isinstance(obj, type)
                and dataclasses.is_dataclass(obj)
                and obj.__module__ == module.__name__
                and (obj.__name__.endswith("Config") or "__post_init__" in vars(obj))
            ):
                assert obj.__name__ not in found, f"two configurations named {obj.__name__}"
                found[obj.__name__] = obj
    return found


CLASSES = _config_classes()
WALKED = sorted(set(CLASSES) - set(_DATA_CONTAINERS))


def test_the_walk_finds_the_configurations():
    assert {"ReconstructionConfig", "TrainConfig", "SliceConfig", "PhantomConfig"} <= set(WALKED)
    assert {"TrainingStackConfig", "ReflectionPlane", "PoseRepresentation"} <= set(WALKED)
    assert {"MaskingConfig", "BrainMaskConfig", "MaskFusionConfig", "StackConfig"} <= set(WALKED)
    listed = set(_DATA_CONTAINERS) | {c for c, _ in _ACCEPTS_ANY_STRING}
    stale = listed - set(CLASSES)
    assert not stale, f"listed but no such class in the package: {sorted(stale)}"
    for name in WALKED:
        assert "__post_init__" in vars(CLASSES[name]), f"{name} does not check its fields"


# --- valid instances and bad values from the annotations -----------------------------------------


def _split_optional(annotation: object) -> tuple[object, bool]:
    """``(X, True)`` for ``X | None``, ``(annotation, False)`` otherwise."""
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(annotation) if a is not type(None)]
        if len(args) == 1 and len(typing.get_args(annotation)) == 2:
            return args[0], True
    return annotation, False


def _is_config(annotation: object) -> bool:
    return isinstance(annotation, type) and dataclasses.is_dataclass(annotation)


def _is_callable(annotation: object) -> bool:
    return typing.get_origin(annotation) is Callable or annotation is Callable


def _hints(cls: type) -> dict[str, object]:
    return typing.get_type_hints(cls)


def _required_value(annotation: object) -> object:
    """A valid value of a field without default, from its annotation."""
    annotation, _ = _split_optional(annotation)
    if _is_config(annotation):
        return _valid(annotation)  # type: ignore[arg-type]
    if typing.get_origin(annotation) is typing.Literal:
        return typing.get_args(annotation)[0]
    if _is_callable(annotation):
        return lambda *args, **kwargs: None
    values = {str: "run", int: 1, float: 1.0, bool: False}
    if annotation in values:
        return values[annotation]  # type: ignore[index]
    raise AssertionError(f"no valid value known for a required field of type {annotation!r}")


def _valid(cls: type) -> object:
    """An instance of ``cls``: its defaults, and a valid value for each field without one."""
    hints = _hints(cls)
    required = {
        f.name: _required_value(hints[f.name])
        for f in dataclasses.fields(cls)
        if f.init and f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
    }
    return cls(**required)


def _items_bad(item: object) -> list[object]:
    """Items of a tuple field that are always wrong."""
    item, _ = _split_optional(item)
    if item is int:
        return ["bad", True, 1.5]
    if item is float:
        return ["bad", True, _NAN, _INF]
    if item is str:
        return [1]
    if _is_config(item):
        return ["bad"]
    raise AssertionError(f"no bad item known for a tuple of {item!r}")


def _bad_values(cls: type, name: str, annotation: object, default: object):
    """``(always_bad, maybe_bad)``: values the field must refuse, and values it may refuse."""
    annotation, optional = _split_optional(annotation)
    if (cls.__name__, name) in _ACCEPTS_ANY_STRING:
        annotation = str
    none = [] if optional else [None]
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Literal:
        return ["bad", 1, *none], []
    if annotation is bool:
        return ["bad", 1, 0.5, *none], []
    if annotation is int:
        return ["bad", "1", True, 1.5, *none], [-1, 0]
    if annotation is float:
        return ["bad", "1.0", True, _NAN, _INF, -_INF, *none], [-1.0, 0.0, -1]
    if annotation is str:
        return [1, ("a",), *none], ["", "bad"]
    if annotation is dict or origin is dict:
        return ["bad", 1, *none], []
    if _is_config(annotation) or _is_callable(annotation):
        return ["bad", 1, *none], []
    if origin is tuple:
        always: list[object] = ["bad", 1, *none]
        maybe: list[object] = [() if default != () else ("bad",)]
        if isinstance(default, tuple):
            maybe.append(list(default))  # some configurations take a list (read from JSON)
        if len(args) == 2 and args[1] is Ellipsis:
            always += [(item,) for item in _items_bad(args[0])]
            if args[0] in (int, float):
                maybe += [(-1,), (0,)]
            return always, maybe
        n = len(args)
        always += [(item,) * n for item in _items_bad(args[0])]
        if n > 1:  # one item too few
            always.append((_required_value(args[0]),) * (n - 1))
        if args[0] in (int, float):
            maybe += [(-1,) * n, (0,) * n] + ([(2, 1)] if n == 2 else [])  # (2, 1): reversed
        return always, maybe
    raise AssertionError(
        f"{cls.__name__}.{name}: no bad values known for its annotation {annotation!r}; teach "
        "tests/test_validation.py its type"
    )


def _cases() -> Iterator[object]:
    for name in WALKED:
        cls = CLASSES[name]
        hints = _hints(cls)
        for f in dataclasses.fields(cls):
            if f.init:
                yield pytest.param(cls, f.name, hints[f.name], id=f"{name}.{f.name}")


def test_every_walked_configuration_builds_from_its_defaults():
    for name in WALKED:
        _valid(CLASSES[name])


@pytest.mark.parametrize(("cls", "name", "annotation"), list(_cases()))
def test_every_field_refuses_a_bad_value_by_name(cls, name, annotation):
    base = _valid(cls)
    default = getattr(base, name)
    always, maybe = _bad_values(cls, name, annotation, default)
    for value in always:
        with pytest.raises(ConfigFieldError) as info:
            dataclasses.replace(base, **{name: value})
        err = info.value
        assert (err.owner, err.field) == (cls.__name__, name), f"{value!r}: {err}"
        assert str(err).startswith(f"{cls.__name__}: '{name}' must be "), str(err)
    for value in maybe:
        try:
            dataclasses.replace(base, **{name: value})
        except ConfigFieldError as err:
            assert (err.owner, err.field) == (cls.__name__, name), f"{value!r}: {err}"
    if _split_optional(annotation)[1]:
        dataclasses.replace(base, **{name: None})  # "not set" is accepted


# --- the checks themselves -----------------------------------------------------------------------


def _refusal(check: Callable[..., object], *args: object, **kwargs: object) -> ConfigFieldError:
    with pytest.raises(ConfigFieldError) as info:
        check("Owner", "field", *args, **kwargs)
    err = info.value
    assert (err.owner, err.field) == ("Owner", "field")
    assert isinstance(err, ValueError)
    assert pickle.loads(pickle.dumps(err)).expected == err.expected
    return err


def test_predicates():
    assert is_integer(3) and is_integer(-1) and not is_integer(True) and not is_integer(3.0)
    assert is_finite_number(3) and is_finite_number(-2.5) and is_finite_number(1e300)
    for bad in (True, False, _NAN, _INF, -_INF, "1", None, (1,)):
        assert not is_finite_number(bad), bad


def test_check_int_edges_and_messages():
    check_int("Owner", "field", 1, minimum=1)
    check_int("Owner", "field", 8, minimum=1, maximum=8)
    check_int("Owner", "field", -5)
    check_int("Owner", "field", None, allow_none=True)
    assert _refusal(check_int, 0, minimum=1).expected == "an integer >= 1"
    assert _refusal(check_int, 9, minimum=1, maximum=8).expected == "an integer in [1, 8]"
    assert _refusal(check_int, 9, maximum=8).expected == "an integer <= 8"
    assert _refusal(check_int, None).expected == "an integer"
    assert _refusal(check_int, "x", allow_none=True).expected == "None or an integer"
    for bad in (True, False, 1.0, 1.5, "1", _NAN):
        _refusal(check_int, bad)
    err = _refusal(check_int, 0, minimum=1)
    assert str(err) == "Owner: 'field' must be an integer >= 1, got 0"


def test_check_number_bounds_open_and_closed():
    check_number("Owner", "field", 0, ge=0)
    check_number("Owner", "field", 1e-9, gt=0)
    check_number("Owner", "field", 1, le=1)
    check_number("Owner", "field", -1e300)
    check_number("Owner", "field", None, gt=0, allow_none=True)
    assert _refusal(check_number, 0.0, gt=0).expected == "a finite number > 0"
    assert _refusal(check_number, -0.1, ge=0).expected == "a finite number >= 0"
    assert _refusal(check_number, 2.0, lt=2).expected == "a finite number < 2"
    assert _refusal(check_number, 1.0, ge=0, lt=1).expected == "in [0, 1)"
    assert _refusal(check_number, -1.0, gt=-1, le=1).expected == "in (-1, 1]"
    assert _refusal(check_number, 1e-7, gt=1e-6).expected == "a finite number > 1e-06"
    for bad in (True, _NAN, _INF, -_INF, "1.0", None):
        assert _refusal(check_number, bad).expected == "a finite number"
    with pytest.raises(TypeError):
        check_number("Owner", "field", 1.0, gt=0, ge=0)


def test_check_fraction():
    for value in (0, 0.5, 1, 1.0):
        check_fraction("Owner", "field", value)
    assert _refusal(check_fraction, 1.5).expected == "in [0, 1]"
    assert _refusal(check_fraction, 0.0, include_zero=False).expected == "in (0, 1]"
    assert _refusal(check_fraction, 1.0, include_one=False).expected == "in [0, 1)"
    assert _refusal(check_fraction, True).expected == "in [0, 1]"
    assert _refusal(check_fraction, _NAN, allow_none=True).expected == "None or in [0, 1]"


def test_check_bool_str_choice_instance_callable():
    check_bool("Owner", "field", False)
    for bad in (0, 1, None, "True"):
        assert _refusal(check_bool, bad).expected == "a bool"
    check_str("Owner", "field", "cpu")
    check_str("Owner", "field", None, allow_none=True)
    for bad in ("", 1, None):
        assert _refusal(check_str, bad).expected == "a non-empty string"
    check_choice("Owner", "field", "sgd", ("adamw", "sgd"))
    err = _refusal(check_choice, "adam", ("adamw", "sgd"))
    assert str(err) == "Owner: 'field' must be one of 'adamw', 'sgd', got 'adam'"
    _refusal(check_choice, 1, ("1", "2"))  # a value of another type is not a choice
    _refusal(check_choice, ["sgd"], ("sgd",))
    check_instance("Owner", "field", {}, dict)
    check_instance("Owner", "field", None, dict, allow_none=True)
    assert _refusal(check_instance, "x", dict).expected == "a dict"
    assert _refusal(check_instance, None, dict).expected == "a dict"
    check_callable("Owner", "field", len)
    assert _refusal(check_callable, "len").expected == "callable"


def test_tuple_checks_return_tuples():
    assert check_int_tuple("Owner", "field", (1, 2), length=2, minimum=1) == (1, 2)
    assert check_int_tuple("Owner", "field", [1, 2], length=2, allow_list=True) == (1, 2)
    assert check_int_tuple("Owner", "field", ()) == ()
    assert check_int_tuple("Owner", "field", None, allow_none=True) is None
    assert _refusal(check_int_tuple, [1, 2], length=2).expected == "a tuple of 2 integers"
    assert _refusal(check_int_tuple, (1, 0), minimum=1).expected == "a tuple of integers >= 1"
    assert _refusal(check_int_tuple, (1, True)).expected == "a tuple of integers"
    assert _refusal(check_int_tuple, (), allow_empty=False).expected == (
        "a non-empty tuple of integers"
    )
    assert check_number_tuple("Owner", "field", (1, 2.5), ge=0) == (1, 2.5)
    err = _refusal(check_number_tuple, (1.0,) * 5, length=(6, 36))
    assert err.expected == "a tuple of 6 or 36 finite numbers"
    assert _refusal(check_number_tuple, (1.0, _NAN)).expected == "a tuple of finite numbers"
    assert _refusal(check_number_tuple, (-1.0,), ge=0).expected == (
        "a tuple of finite numbers >= 0"
    )
    assert _refusal(check_number_tuple, "ab").expected == "a tuple of finite numbers"
    assert check_instance_tuple("Owner", "field", ["a"], str, allow_list=True) == ("a",)
    assert _refusal(check_instance_tuple, ("a", 1), str).expected == "a tuple of str"


def test_check_range():
    assert check_range("Owner", "field", (1.0, 1.0), gt=0) == (1.0, 1.0)
    assert check_range("Owner", "field", [0, 180], ge=0, le=180, allow_list=True) == (0, 180)
    assert check_range("Owner", "field", None, allow_none=True) is None
    err = _refusal(check_range, (2.0, 1.0), gt=0)
    assert err.expected == "a tuple (low, high) of finite numbers with 0 < low <= high"
    for bad in ((0.0, 1.0), (1.0,), (1.0, 2.0, 3.0), [1.0, 2.0], (1.0, _INF), "12", None):
        _refusal(check_range, bad, gt=0)
    err = _refusal(check_range, (0, 181), ge=0, le=180)
    assert err.expected == "a tuple (low, high) of finite numbers with 0 <= low <= high <= 180"
    err = _refusal(check_range, (1, 2.5), ge=1, integer=True)
    assert err.expected == "a tuple (low, high) of integers with 1 <= low <= high"
    _refusal(check_range, (True, 2), integer=True)
    assert _refusal(check_range, (2, 1)).expected.endswith("with low <= high")


# --- the command line's side ---------------------------------------------------------------------


def _cli_message(options: dict[str, str], err: ConfigFieldError) -> str:
    with pytest.raises(CliError) as info, option_errors(options):
        raise err
    assert info.value.__cause__ is err
    return str(info.value)


def test_option_errors_names_the_option():
    err = ConfigFieldError("TrainConfig", "steps", "an integer >= 1", 0)
    assert _cli_message({"steps": "--steps"}, err) == "--steps must be an integer >= 1, got 0"
    ranged = ConfigFieldError("SimulationConfig", "stack_turn_deg", "a tuple (low, high)", (5, 1))
    assert (
        _cli_message({"stack_turn_deg": "--t"}, ranged)
        == "--t must be a tuple (low, high), got 5 1"
    )
    optional = ConfigFieldError("C", "template", "None or an integer >= 0", -1)
    assert _cli_message({"template": "--template"}, optional).startswith(
        "--template must be an integer >= 0, got -1"
    )
    # "Owner.field" keys first; a field without an option keeps the library's message
    options = {"steps": "--train-steps", "LossDemoConfig.steps": "--steps"}
    loss = ConfigFieldError("LossDemoConfig", "steps", "an integer >= 1", 0)
    assert _cli_message(options, loss).startswith("--steps must")
    assert _cli_message(options, err).startswith("--train-steps must")
    unmapped = ConfigFieldError("TrainConfig", "amp", "a bool", 1)
    assert _cli_message(options, unmapped) == "TrainConfig: 'amp' must be a bool, got 1"


def test_option_errors_lets_other_errors_through():
    with pytest.raises(KeyError), option_errors({"steps": "--steps"}):
        raise KeyError("steps")
    with option_errors({}):
        pass
