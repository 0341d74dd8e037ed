"""Slice-pose models shipped with the package, loadable by name.

The shipped model lives in the package-data folder ``models/pretrained/default/``, a checkpoint
folder in the layout of :mod:`svr.models.checkpoint` (``model.safetensors`` in float16,
``config.json`` with the model configuration and its provenance) plus a ``README.md`` with its
training command, data licence and evaluation. It is written by
:func:`svr.models.pretrained.export.export_model` (``svr export-model``) and
read, like any checkpoint, by :func:`svr.models.predict.load_pose_model`, which accepts the name
:data:`DEFAULT_MODEL` for it (:func:`svr.models.checkpoint.resolve_model_path`): safetensors and
JSON only, so loading never executes code, and the float16 weights come back in their original
float32.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

from svr.errors import CheckpointError

__all__ = [
    "BRAIN_MASK_FOLDER",
    "DEFAULT_MODEL",
    "MAX_MODEL_BYTES",
    "SLICE_POSE_MODEL",
    "SLICE_REFINER_FOLDER",
    "SLICE_REFINER_STAGES",
    "STACK_POSE_FOLDER",
    "brain_mask_model_path",
    "default_model_path",
    "slice_refiner_paths",
    "stack_pose_model_path",
]

DEFAULT_MODEL = "default"
"""The name that stands for the shipped slice-pose model wherever a checkpoint folder is accepted
(the first model the project shipped, hence the name)."""

SLICE_POSE_MODEL = "slice-pose"
"""Another name for the shipped slice-pose model, beside the shipped ``"stack-pose"`` one."""

MAX_MODEL_BYTES = 10_000_000
"""Largest size of a shipped model's files (weights and config), bytes (10 MB)."""


def default_model_path() -> Path:
    """The folder of the shipped model inside the installed package (it may be absent).

    Raises:
        CheckpointError: If the package is not installed as plain files (e.g. in a zip archive),
            so that the weights cannot be opened by path.
    """
    return _shipped_folder(DEFAULT_MODEL)


BRAIN_MASK_FOLDER = "brain_mask"
"""The package-data folder of the shipped brain-mask model (:mod:`svr.masking`)."""


def brain_mask_model_path() -> Path:
    """The folder of the shipped brain-mask model inside the installed package.

    Raises:
        CheckpointError: If the package is not installed as plain files.
    """
    return _shipped_folder(BRAIN_MASK_FOLDER)


STACK_POSE_FOLDER = "stack_pose"
"""The package-data folder of the shipped stack-pose model (:mod:`svr.models.stack_pose`)."""


def stack_pose_model_path() -> Path:
    """The folder of the shipped stack-pose model inside the installed package (it may be absent).

    Raises:
        CheckpointError: If the package is not installed as plain files.
    """
    return _shipped_folder(STACK_POSE_FOLDER)


SLICE_REFINER_FOLDER = "slice_refiner"
"""The package-data folder of the shipped slice refiner (:mod:`svr.models.slice_refiner`)."""

SLICE_REFINER_STAGES = ("wide", "fine")
"""The shipped slice refiner's stages, in the order they are applied: ``wide`` trained on
residual rotations up to 30 degrees, ``fine`` on ones up to 10 (each a sub-folder)."""


def slice_refiner_paths() -> tuple[Path, ...]:
    """The folders of the shipped slice refiner's stages (:data:`SLICE_REFINER_STAGES`' order).

    Raises:
        CheckpointError: If the package is not installed as plain files.
    """
    folder = _shipped_folder(SLICE_REFINER_FOLDER)
    return tuple(folder / stage for stage in SLICE_REFINER_STAGES)


def _shipped_folder(name: str) -> Path:
    folder = resources.files(__name__).joinpath(name)
    if not isinstance(folder, Path):
        raise CheckpointError(
            str(folder), "the package is not installed as files; cannot open the shipped model"
        )
    return folder
