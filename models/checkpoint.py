"""Model checkpoints: safetensors weights, a JSON config and an optional training state.

A checkpoint is a folder, written atomically (:func:`svr.files.atomic_directory`)::

    step_000001000/
      model.safetensors   the state dict: contiguous CPU tensors (float16 in half precision)
      config.json         the caller's config plus a "checkpoint" section (versions, hashes)
      training_state.pt   optional: optimizer and scheduler states, step, RNG states

Loading never executes code: the weights are read with safetensors, the config with :mod:`json`
and the training state with ``torch.load(weights_only=True)``, which refuses any pickled object
other than tensors and plain data. The config records the SHA-256 of the other files, so a modified
or truncated file is reported instead of loaded.

Training runs write ``folder/step_NNNNNNNNN/`` checkpoints (:func:`checkpoint_name`), resume from
:func:`latest_checkpoint` and bound their disk use with :func:`prune_checkpoints`.
"""

from __future__ import annotations

import json
import logging
import os
import pickle
import re
import shutil
from collections import OrderedDict
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Literal

import safetensors.torch
import torch
from safetensors import SafetensorError, safe_open

from svr import __version__ as svr_version
from svr.errors import CheckpointError
from svr.files import atomic_directory, file_sha256
from svr.models import pretrained

__all__ = [
    "CHECKPOINT_CONFIG",
    "CHECKPOINT_WEIGHTS",
    "FORMAT_VERSION",
    "TRAINING_STATE",
    "Checkpoint",
    "CheckpointError",
    "checkpoint_name",
    "latest_checkpoint",
    "load_checkpoint",
    "prune_checkpoints",
    "save_checkpoint",
]

CHECKPOINT_WEIGHTS = "model.safetensors"
CHECKPOINT_CONFIG = "config.json"
TRAINING_STATE = "training_state.pt"
FORMAT_VERSION = 1
"""Version of the checkpoint layout, stored in ``config["checkpoint"]["format_version"]``."""

_SECTION = "checkpoint"
_DTYPES_METADATA = "original_dtypes"
_HALF_FROM = (torch.float32, torch.float64)
_STEP_FOLDER = re.compile(r"step_(\d{9,})")
_PLAIN_TYPES = (bool, int, float, str, type(None))
_TENSOR_TYPES = (torch.Tensor, torch.nn.Parameter)
_MAPPING_TYPES = (dict, OrderedDict)
_SEQUENCE_TYPES = (list, tuple)

log = logging.getLogger(__name__)


@dataclass
class Checkpoint:
    """A loaded checkpoint.

    Attributes:
        path: Its folder.
        state_dict: The weights, in their original dtypes, on the requested device.
        config: The saved config, with the ``"checkpoint"`` section written by
            :func:`save_checkpoint` (format and library versions, creation time, dtypes, hashes).
        training_state: The saved training state, or ``None`` when not requested.
    """

    path: Path
    state_dict: dict[str, torch.Tensor]
    config: dict[str, Any]
    training_state: dict[str, Any] | None


def checkpoint_name(step: int) -> str:
    """The folder name of the checkpoint taken after ``step`` training steps: ``step_%09d``.

    Raises:
        ValueError: If ``step`` is negative.
    """
    if step < 0:
        raise ValueError(f"checkpoint step must be >= 0, got {step}")
    return f"step_{step:09d}"


def save_checkpoint(
    path: str | os.PathLike[str],
    state_dict: dict[str, torch.Tensor],
    config: dict[str, Any],
    *,
    training_state: dict[str, Any] | None = None,
    half_precision: bool = False,
    overwrite: bool = False,
) -> Path:
    """Write a checkpoint folder atomically: a reader never sees a partial checkpoint.

    Args:
        path: The checkpoint folder to create; its parent folder must exist.
        state_dict: The weights (``module.state_dict()``), saved as contiguous CPU copies.
        config: JSON-serialisable description of the model (architecture, representation, input
            size and spacing, metric weights, training data). The key ``"checkpoint"`` is reserved
            for the section this function adds.
        training_state: What resuming needs (``optimizer.state_dict()``,
            ``scheduler.state_dict()``, step, RNG states as tensors), made only of tensors, bools,
            ints, floats, strings, ``None`` and dicts, lists and tuples of them.
        half_precision: Store float32 and float64 weights as float16 (about half the size); their
            original dtypes are recorded and restored on loading.
        overwrite: Whether an existing checkpoint folder may be replaced.

    Returns:
        The checkpoint folder.

    Raises:
        CheckpointError: If a weight is not a dense tensor, a weight overflows float16, the config
            is not JSON-serialisable or uses the reserved key, or the training state holds another
            type of object.
        OutputExistsError: If the folder exists and ``overwrite`` is false.
        FileNotFoundError: If the parent folder does not exist.
    """
    out = Path(path)
    tensors, dtypes = _prepare_weights(out, state_dict, half_precision)
    if _SECTION in config:
        raise CheckpointError(out, f'config key "{_SECTION}" is reserved for checkpoint metadata')
    try:
        json.dumps(config, allow_nan=False)
    except (TypeError, ValueError) as exc:
        raise CheckpointError(out, f"config is not JSON-serialisable: {exc}") from exc
    if training_state is not None:
        _check_training_state(out, training_state, "training_state")

    with atomic_directory(out, overwrite) as tmp:
        safetensors.torch.save_file(
            tensors, tmp / CHECKPOINT_WEIGHTS, metadata={_DTYPES_METADATA: json.dumps(dtypes)}
        )
        state_sha256 = None
        if training_state is not None:
            torch.save(training_state, tmp / TRAINING_STATE)
            state_sha256 = file_sha256(tmp / TRAINING_STATE)
        section = {
            "format_version": FORMAT_VERSION,
            "svr_version": svr_version,
            "torch_version": torch.__version__,
            "created_utc": datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "half_precision": half_precision,
            "dtypes": dtypes,
            "weights_sha256": file_sha256(tmp / CHECKPOINT_WEIGHTS),
            "training_state_sha256": state_sha256,
        }
        text = json.dumps({**config, _SECTION: section}, indent=2, allow_nan=False)
        (tmp / CHECKPOINT_CONFIG).write_text(text + "\n", encoding="utf-8")
    return out


def load_checkpoint(
    path: str | os.PathLike[str],
    map_location: str | torch.device = "cpu",
    *,
    with_training_state: bool = False,
) -> Checkpoint:
    """Read a checkpoint written by :func:`save_checkpoint`, verifying its files first.

    Args:
        path: The checkpoint folder.
        map_location: Device to load the tensors onto.
        with_training_state: Also load ``training_state.pt`` (required to exist).

    Returns:
        The weights in their original dtypes, the config and the training state if requested.

    Raises:
        CheckpointError: If ``map_location`` is not an available device, the folder or a file is
            missing, the config is not valid JSON or lacks the checkpoint section, a file does not
            match its recorded SHA-256, the weights file is corrupted, or the training state holds
            anything but tensors and plain data (nothing in it is executed).
    """
    folder = Path(path)
    device = _device(folder, map_location)
    config = _verified_config(folder, "required" if with_training_state else "skip")
    state_dict = _load_weights(folder / CHECKPOINT_WEIGHTS, device)
    training_state = (
        _load_training_state(folder / TRAINING_STATE, device) if with_training_state else None
    )
    return Checkpoint(folder, state_dict, config, training_state)


def latest_checkpoint(folder: str | os.PathLike[str]) -> Path | None:
    """The complete checkpoint with the highest step in ``folder``, to resume from.

    Only ``step_NNNNNNNNN`` folders count (temporary folders of unfinished writes do not); one with
    missing or modified files is skipped with a logged warning.

    Args:
        folder: The folder holding the checkpoints of a run.

    Returns:
        The checkpoint folder, or ``None`` if ``folder`` does not exist or holds no complete
        checkpoint.

    Raises:
        CheckpointError: If ``folder`` exists but is not a folder.
    """
    for path in _step_folders(folder):
        if _is_complete(path):
            return path
    return None


def resolve_model_path(path_or_name: str | os.PathLike[str]) -> Path:
    """The checkpoint folder that a model argument (``--model``, ``--checkpoints``) names.

    One meaning everywhere: the names :data:`svr.models.pretrained.DEFAULT_MODEL` (``"default"``)
    and :data:`~svr.models.pretrained.SLICE_POSE_MODEL` (``"slice-pose"``) are the shipped
    slice-pose model (a folder literally named so is given as ``./default``); a
    folder holding ``config.json`` is that checkpoint; a training run folder (``checkpoints/``
    inside) or a folder of ``step_*`` checkpoints stands for its newest complete checkpoint.

    Args:
        path_or_name: The name or folder.

    Returns:
        The checkpoint folder.

    Raises:
        CheckpointError: Naming the folder, if it does not exist, holds no checkpoint, or is the
            shipped model's and its files are not installed.
    """
    if isinstance(path_or_name, str) and path_or_name in (
        pretrained.DEFAULT_MODEL,
        pretrained.SLICE_POSE_MODEL,
    ):
        folder = pretrained.default_model_path()
        missing = [f for f in (CHECKPOINT_WEIGHTS, CHECKPOINT_CONFIG) if not (folder / f).is_file()]
        if missing:
            raise CheckpointError(
                folder,
                f"the shipped default model is not installed (missing {', '.join(missing)}); "
                "export one with svr export-model or give a checkpoint folder",
            )
        return folder
    path = Path(path_or_name)
    if not path.is_dir():
        problem = (
            "not a checkpoint folder (a file)"
            if path.exists()
            else "checkpoint folder does not exist"
        )
        raise CheckpointError(path, problem)
    if (path / CHECKPOINT_CONFIG).is_file():
        return path
    for folder in (path / "checkpoints", path):
        latest = latest_checkpoint(folder) if folder.is_dir() else None
        if latest is not None:
            return latest
    raise CheckpointError(
        path,
        f"missing {CHECKPOINT_CONFIG}, and no step_*/ or checkpoints/step_*/ inside: not a "
        "checkpoint or training run folder",
    )


def prune_checkpoints(folder: str | os.PathLike[str], keep: int) -> None:
    """Delete the checkpoints older than the newest ``keep`` complete ones.

    Incomplete checkpoints newer than those are left in place (and skipped by
    :func:`latest_checkpoint`), as are temporary folders, which may belong to a write in progress.
    Nothing is deleted while fewer than ``keep`` complete checkpoints exist.

    Args:
        folder: The folder holding the checkpoints of a run.
        keep: How many complete checkpoints to keep, >= 1.

    Raises:
        ValueError: If ``keep`` is less than 1.
        CheckpointError: If ``folder`` exists but is not a folder.
    """
    if keep < 1:
        raise ValueError(f"keep must be >= 1, got {keep}")
    kept = 0
    for path in _step_folders(folder):
        if kept >= keep:
            shutil.rmtree(path)
        elif _is_complete(path):
            kept += 1


def _prepare_weights(
    out: Path, state_dict: dict[str, torch.Tensor], half_precision: bool
) -> tuple[dict[str, torch.Tensor], dict[str, str]]:
    """CPU copies of the weights to store, and the names of their original dtypes."""
    tensors, dtypes = {}, {}
    for name, tensor in state_dict.items():
        if not isinstance(name, str) or not isinstance(tensor, torch.Tensor):
            raise CheckpointError(
                out, f"state_dict entry {name!r} is a {type(tensor).__name__}, not a tensor"
            )
        if tensor.layout != torch.strided:
            raise CheckpointError(out, f"weight {name!r} is a {tensor.layout} tensor, not dense")
        dtype = torch.float16 if half_precision and tensor.dtype in _HALF_FROM else tensor.dtype
        # Always a copy: safetensors refuses tensors that share memory (tied weights, views).
        stored = tensor.detach().to(
            device="cpu", dtype=dtype, copy=True, memory_format=torch.contiguous_format
        )
        if dtype != tensor.dtype and int(stored.isinf().sum()) > int(tensor.isinf().sum()):
            raise CheckpointError(out, f"weight {name!r} overflows float16; save in full precision")
        tensors[name] = stored
        dtypes[name] = str(tensor.dtype).removeprefix("torch.")
    return tensors, dtypes


def _check_training_state(out: Path, value: Any, where: str) -> None:
    """Raise unless ``value`` holds only what ``torch.load(weights_only=True)`` reads back."""
    kind = type(value)
    if kind in _TENSOR_TYPES or kind in _PLAIN_TYPES:
        return
    if kind in _SEQUENCE_TYPES:
        for i, item in enumerate(value):
            _check_training_state(out, item, f"{where}[{i}]")
        return
    if kind in _MAPPING_TYPES:
        for key, item in value.items():
            if type(key) not in (str, int):
                raise CheckpointError(
                    out, f"{where} has a key of type {type(key).__name__}; use str or int keys"
                )
            _check_training_state(out, item, f"{where}[{key!r}]")
        return
    raise CheckpointError(
        out,
        f"{where} is a {kind.__module__}.{kind.__qualname__}; a training state holds only tensors, "
        "bools, ints, floats, strings, None and dicts, lists and tuples of them",
    )


def _device(folder: Path, map_location: str | torch.device) -> torch.device:
    """``map_location`` as a device, checked to be usable here."""
    try:
        device = torch.device(map_location)
        torch.empty(0, device=device)
    except (RuntimeError, TypeError, AssertionError, NotImplementedError) as exc:
        raise CheckpointError(
            folder, f"map_location {map_location!r} is not a usable device: {_summary(exc)}"
        ) from exc
    return device


def _verified_config(
    folder: Path, training_state: Literal["required", "if_recorded", "skip"]
) -> dict[str, Any]:
    """The config of a checkpoint folder, after checking its files against the recorded hashes.

    Args:
        folder: The checkpoint folder.
        training_state: Whether ``training_state.pt`` must exist and match its hash
            (``"required"``), must match its hash if the config records one (``"if_recorded"``),
            or is not checked (``"skip"``).
    """
    if not folder.exists():
        raise CheckpointError(folder, "checkpoint folder does not exist")
    if not folder.is_dir():
        raise CheckpointError(folder, "not a checkpoint folder (a file)")
    file = folder / CHECKPOINT_CONFIG
    if not file.is_file():
        raise CheckpointError(folder, f"missing {CHECKPOINT_CONFIG}")
    try:
        config = json.loads(file.read_bytes())
    except ValueError as exc:
        raise CheckpointError(file, f"not valid JSON: {exc}") from exc
    section = config.get(_SECTION) if isinstance(config, dict) else None
    if not isinstance(section, dict):
        raise CheckpointError(file, f'no "{_SECTION}" section; not written by save_checkpoint')
    version = section.get("format_version")
    if version != FORMAT_VERSION:
        raise CheckpointError(
            file,
            f"checkpoint format version {version!r} is not supported (expected {FORMAT_VERSION})",
        )
    _verify_file(folder / CHECKPOINT_WEIGHTS, section.get("weights_sha256"))
    state_sha256 = section.get("training_state_sha256")
    if training_state == "required" and state_sha256 is None:
        raise CheckpointError(folder, f"saved without a training state ({TRAINING_STATE})")
    if training_state != "skip" and state_sha256 is not None:
        _verify_file(folder / TRAINING_STATE, state_sha256)
    return config


def _verify_file(file: Path, sha256: object) -> None:
    """Raise unless ``file`` exists and has the SHA-256 recorded in the config."""
    if not isinstance(sha256, str):
        raise CheckpointError(file.parent / CHECKPOINT_CONFIG, f"no SHA-256 for {file.name}")
    if not file.is_file():
        raise CheckpointError(file.parent, f"missing {file.name}")
    if file_sha256(file) != sha256:
        raise CheckpointError(
            file, f"does not match its SHA-256 in {CHECKPOINT_CONFIG} (modified or corrupted)"
        )


def _load_weights(file: Path, device: torch.device) -> dict[str, torch.Tensor]:
    """The tensors of a safetensors file on ``device``, cast back to their recorded dtypes."""
    try:
        with safe_open(file, framework="pt", device=str(device)) as f:
            record = (f.metadata() or {}).get(_DTYPES_METADATA)
            tensors = {name: f.get_tensor(name) for name in f.keys()}  # noqa: SIM118
    except (SafetensorError, OSError) as exc:
        raise CheckpointError(file, f"corrupted safetensors file: {_summary(exc)}") from exc
    try:
        # a missing record (None) raises TypeError, reported below
        recorded = json.loads(record)  # type: ignore[arg-type]
        dtypes = {name: getattr(torch, dtype) for name, dtype in recorded.items()}
    except (TypeError, ValueError, AttributeError) as exc:
        raise CheckpointError(file, "no valid record of the original dtypes") from exc
    if dtypes.keys() != tensors.keys() or not all(
        isinstance(d, torch.dtype) for d in dtypes.values()
    ):
        raise CheckpointError(file, "the record of the original dtypes does not match the tensors")
    return {name: tensors[name].to(dtype) for name, dtype in dtypes.items()}  # saved order


def _load_training_state(file: Path, device: torch.device) -> dict[str, Any]:
    """A training state read with ``torch.load(weights_only=True)``: no code is executed."""
    try:
        state = torch.load(file, map_location=device, weights_only=True)
    except pickle.UnpicklingError as exc:
        raise CheckpointError(
            file, f"training state refused by the safe unpickler: {_summary(exc)}"
        ) from exc
    except (RuntimeError, EOFError, OSError) as exc:
        raise CheckpointError(file, f"unreadable training state: {_summary(exc)}") from exc
    if not isinstance(state, dict):
        raise CheckpointError(file, f"training state is a {type(state).__name__}, not a dict")
    return state


def _summary(exc: BaseException) -> str:
    """A one-line account of an error from torch or safetensors (often several lines long)."""
    lines = [line.strip() for line in str(exc).splitlines() if line.strip()]
    if isinstance(exc, pickle.UnpicklingError) and len(lines) >= 3:
        return lines[-2]  # torch puts the detail between a generic header and a link to its docs
    return lines[0].split(". ")[0] if lines else type(exc).__name__


def _step_folders(folder: str | os.PathLike[str]) -> list[Path]:
    """The ``step_NNNNNNNNN`` folders in ``folder``, newest (highest step) first."""
    root = Path(folder)
    if not root.exists():
        return []
    if not root.is_dir():
        raise CheckpointError(root, "not a folder of checkpoints (a file)")
    steps = []
    for entry in root.iterdir():
        match = _STEP_FOLDER.fullmatch(entry.name)
        if match and entry.is_dir():
            steps.append((int(match.group(1)), entry))
    return [entry for _, entry in sorted(steps, reverse=True)]


def _is_complete(path: Path) -> bool:
    """Whether a checkpoint folder has all its files, matching their recorded hashes."""
    try:
        _verified_config(path, "if_recorded")
    except CheckpointError as exc:
        log.warning("skipping incomplete checkpoint: %s", exc)
        return False
    return True
