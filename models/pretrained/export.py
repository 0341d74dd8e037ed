"""Export a trained checkpoint as a small, self-describing model to ship or share.

An exported model is a checkpoint folder (:mod:`svr.models.checkpoint`) without a training state:
``model.safetensors`` with the weights in float16 (their float32 dtype recorded, so loading casts
them back) and ``config.json`` holding exactly what :func:`svr.models.predict.load_pose_model` needs
(the ``"model"`` section), the source run's ``"training"`` section, the caller's
``"provenance"`` and an ``"export"`` section (source checkpoint, its step and weights hash, library
versions). It is written atomically and is at most :data:`svr.models.pretrained.MAX_MODEL_BYTES`.
"""

from __future__ import annotations

import json
import os
import platform
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import safetensors
import torch

from svr import __version__ as svr_version
from svr.models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from svr.models.network import checkpoint_model_config
from svr.models.predict import pose_model_from_checkpoint
from svr.models.pretrained import MAX_MODEL_BYTES

__all__ = [
    "REQUIRED_PROVENANCE",
    "export_model",
    "export_slice_refiner",
    "export_stack_pose_model",
]

REQUIRED_PROVENANCE = ("training_command", "data")
"""Keys that the ``provenance`` of :func:`export_model` must have."""

_HALF = torch.float16
_BYTES_PER_TENSOR_RECORD = 512  # a tensor's entries in the safetensors header and the config


def _stored_bytes(state_dict: dict[str, torch.Tensor]) -> int:
    """Bytes of the tensors once floating-point ones are stored in float16."""
    return sum(
        t.numel() * (_HALF.itemsize if t.is_floating_point() else t.element_size())
        for t in state_dict.values()
    )


def _check_provenance(out: Path, provenance: object) -> dict[str, Any]:
    """``provenance`` itself, checked to be a JSON-serialisable dict with the required keys."""
    if not isinstance(provenance, dict):
        raise CheckpointError(out, f"provenance must be a dict, got {type(provenance).__name__}")
    missing = [key for key in REQUIRED_PROVENANCE if not provenance.get(key)]
    if missing:
        raise CheckpointError(
            out,
            f"provenance must record {', '.join(repr(k) for k in REQUIRED_PROVENANCE)}; "
            f"missing or empty: {', '.join(missing)}",
        )
    try:
        json.dumps(provenance, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(out, f"provenance is not JSON-serialisable: {exc}") from exc
    return provenance


def _export_record() -> dict[str, Any]:
    """The weights' stored type and the versions of what exported them."""
    return {
        "weights_dtype": str(_HALF).removeprefix("torch."),
        "versions": {
            "fetal_svr": svr_version,
            "torch": torch.__version__,
            "safetensors": safetensors.__version__,
            "numpy": np.__version__,
            "python": platform.python_version(),
        },
    }


def _write_export(
    source: Path,
    out: Path,
    state_dict: dict[str, torch.Tensor],
    config: dict[str, Any],
    overwrite: bool,
    hint: str,
) -> Path:
    """Save a float16 model folder once its size is known to stay within the limit."""
    size = _stored_bytes(state_dict) + len(json.dumps(config, indent=2).encode())
    size += _BYTES_PER_TENSOR_RECORD * len(state_dict)
    if size > MAX_MODEL_BYTES:
        raise CheckpointError(
            source,
            f"the exported model would take about {size / 1e6:.2f} MB; it must stay within "
            f"{MAX_MODEL_BYTES / 1e6:g} MB ({hint})",
        )
    return save_checkpoint(out, state_dict, config, half_precision=True, overwrite=overwrite)


def export_model(
    checkpoint_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    provenance: dict[str, Any],
    overwrite: bool = False,
) -> Path:
    """Write a checkpoint's network as a float16 model folder with its provenance.

    Args:
        checkpoint_dir: A checkpoint folder written by ``svr train`` (its config has a ``"model"``
            section and the weights fit it).
        out_dir: The model folder to create; its parent folder must exist. It must not be
            ``checkpoint_dir``.
        provenance: JSON-serialisable description of how the model was made, stored verbatim as
            the config's ``"provenance"``; must have non-empty ``"training_command"`` (the exact
            command) and ``"data"`` (the training data, its source and licence) entries
            (:data:`REQUIRED_PROVENANCE`).
        overwrite: Whether an existing ``out_dir`` (the whole folder) may be replaced.

    Returns:
        ``out_dir``.

    Raises:
        CheckpointError: Naming the path, if the checkpoint cannot be loaded as a slice-pose
            model, ``provenance`` lacks a required key or is not JSON-serialisable, a weight
            overflows float16, or the model would exceed
            :data:`~svr.models.pretrained.MAX_MODEL_BYTES` (checked before anything is written).
        OutputExistsError: If ``out_dir`` exists and ``overwrite`` is false.
        ValueError: If ``out_dir`` is ``checkpoint_dir``.
        FileNotFoundError: If the parent folder of ``out_dir`` does not exist.
    """
    source, out = Path(checkpoint_dir), Path(out_dir)
    if out.resolve() == source.resolve():
        raise ValueError(f"export_model(): 'out_dir' {out} is the checkpoint folder itself")
    provenance = _check_provenance(out, provenance)
    checkpoint = load_checkpoint(source)
    model = pose_model_from_checkpoint(checkpoint)
    state_dict = model.state_dict()
    training = checkpoint.config.get("training")
    export_config = {
        **checkpoint_model_config(model.config),
        "metric_weights": checkpoint.config.get("metric_weights"),
        "training": training,
        "provenance": provenance,
        "export": {
            "source_checkpoint": str(source),
            "source_step": training.get("step") if isinstance(training, dict) else None,
            "source_weights_sha256": checkpoint.config["checkpoint"]["weights_sha256"],
            **_export_record(),
        },
    }
    return _write_export(
        source, out, state_dict, export_config, overwrite, "train a smaller model: --width, --depth"
    )


def export_stack_pose_model(
    checkpoint_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    provenance: dict[str, Any],
    overwrite: bool = False,
) -> Path:
    """Write a stack-pose checkpoint as a float16 model folder with its provenance.

    Args:
        checkpoint_dir: A checkpoint folder (or training run folder) of ``svr train-stack-pose``.
        out_dir: The model folder to create (not ``checkpoint_dir``).
        provenance: As for :func:`export_model` (``"training_command"`` and ``"data"`` required).
        overwrite: Whether an existing ``out_dir`` may be replaced.

    Returns:
        ``out_dir``.

    Raises:
        CheckpointError: If the checkpoint is not a stack-pose model, the provenance is
            incomplete, or the model would exceed :data:`~svr.models.pretrained.MAX_MODEL_BYTES`.
    """
    from svr.models.stack_pose import load_stack_pose_model

    return _export_network(
        "export_stack_pose_model",
        "stack_pose",
        load_stack_pose_model,
        checkpoint_dir,
        out_dir,
        provenance,
        overwrite,
        "train a smaller model: --width",
    )


def export_slice_refiner(
    checkpoint_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    *,
    provenance: dict[str, Any],
    overwrite: bool = False,
) -> Path:
    """Write a slice-refiner checkpoint (:mod:`svr.models.slice_refiner`) as a float16 model folder.

    Args:
        checkpoint_dir: A checkpoint folder (or training run folder) of a slice refiner.
        out_dir: The model folder to create (not ``checkpoint_dir``).
        provenance: As for :func:`export_model` (``"training_command"`` and ``"data"`` required).
        overwrite: Whether an existing ``out_dir`` may be replaced.

    Returns:
        ``out_dir``.

    Raises:
        CheckpointError: If the checkpoint is not a slice refiner, the provenance is incomplete,
            or the model would exceed :data:`~svr.models.pretrained.MAX_MODEL_BYTES`.
    """
    from svr.models.slice_refiner import SLICE_REFINER, load_slice_refiner

    return _export_network(
        "export_slice_refiner",
        SLICE_REFINER,
        load_slice_refiner,
        checkpoint_dir,
        out_dir,
        provenance,
        overwrite,
        "a narrower backbone",
    )


def _export_network(
    caller: str,
    architecture: str,
    load: Callable[[Path], torch.nn.Module],
    checkpoint_dir: str | os.PathLike[str],
    out_dir: str | os.PathLike[str],
    provenance: dict[str, Any],
    overwrite: bool,
    hint: str,
) -> Path:
    """Export a network whose loader checks its architecture and whose config has ``to_dict``."""
    source, out = Path(checkpoint_dir), Path(out_dir)
    if out.resolve() == source.resolve():
        raise ValueError(f"{caller}(): 'out_dir' {out} is the checkpoint folder")
    provenance = _check_provenance(out, provenance)
    model = load(source)
    export_config = {
        "architecture": architecture,
        "model": model.config.to_dict(),  # type: ignore[union-attr, operator]
        "provenance": provenance,
        "export": {
            "source_checkpoint": str(source),
            **_export_record(),
        },
    }
    return _write_export(source, out, model.state_dict(), export_config, overwrite, hint)
