"""Typed errors that the library raises and the command line words (no CLI text below the CLI)."""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["CheckpointError", "ConfigFieldError"]


class ConfigFieldError(ValueError):
    """A configuration field has a value outside what it accepts.

    The message is ``"<owner>: '<field>' must be <expected>, got <value>"``; the attributes let a
    caller (the CLI) name its own option instead of the field.

    Attributes:
        owner: The configuration class, e.g. ``"ReconstructionConfig"``.
        field: The field name.
        expected: What the field accepts, e.g. ``"in [-1, 1]"``.
        value: The value given.
    """

    def __init__(self, owner: str, field: str, expected: str, value: object) -> None:
        self.owner = owner
        self.field = field
        self.expected = expected
        self.value = value
        super().__init__(f"{owner}: '{field}' must be {expected}, got {value!r}")

    def __reduce__(self) -> tuple[type[ConfigFieldError], tuple[str, str, str, object]]:
        return type(self), (self.owner, self.field, self.expected, self.value)


class CheckpointError(ValueError):
    """A checkpoint cannot be written or read; the message names the path and the problem.

    Attributes:
        path: The checkpoint folder or file concerned.
        problem: What is wrong with it.
    """

    def __init__(self, path: str | os.PathLike[str], problem: str) -> None:
        self.path = Path(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self) -> tuple[type[CheckpointError], tuple[Path, str]]:
        return type(self), (self.path, self.problem)
