"""The brain-mask networks (a localiser and a segmenter U-Net) and their checkpoints."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch
from torch import nn

from svr.masking.config import BrainMaskConfig
from svr.models.checkpoint import (
    CheckpointError,
    load_checkpoint,
    resolve_model_path,
    save_checkpoint,
)
from svr.models.pretrained import DEFAULT_MODEL, brain_mask_model_path
from svr.models.segmentation import BrainUNet

__all__ = ["BrainMasker", "load_brain_masker", "save_brain_masker"]

_ARCHITECTURE = "brain_masker"


class BrainMasker(nn.Module):
    """The localiser and the segmenter U-Nets with their :class:`BrainMaskConfig`.

    Args:
        config: Canvases and network shapes; ``None`` for ``BrainMaskConfig()``.

    Attributes:
        config: The configuration.
        localiser: Brain logits on the coarse whole-slice canvas (or its tiles).
        segmenter: Brain logits on the fine canvas centred on the brain.
    """

    def __init__(self, config: BrainMaskConfig | None = None) -> None:
        super().__init__()
        self.config = BrainMaskConfig() if config is None else config
        self.localiser = BrainUNet(self.config.localiser)
        self.segmenter = BrainUNet(self.config.segmenter)


def save_brain_masker(
    masker: BrainMasker,
    path: str | os.PathLike[str],
    provenance: dict[str, Any] | None = None,
    overwrite: bool = False,
) -> Path:
    """Write a masker as a checkpoint folder (float16 safetensors + JSON config).

    Args:
        masker: The networks.
        path: The checkpoint folder to create.
        provenance: JSON data recorded beside the config (training command, data, figures).
        overwrite: Whether an existing folder may be replaced.

    Returns:
        The folder.
    """
    config = {"architecture": _ARCHITECTURE, "brain_mask": masker.config.to_dict()}
    if provenance is not None:
        config["provenance"] = provenance
    state = {k: v.detach().cpu() for k, v in masker.state_dict().items()}
    return save_checkpoint(path, state, config, half_precision=True, overwrite=overwrite)


def load_brain_masker(
    path_or_name: str | os.PathLike[str] = "default", device: torch.device | str = "cpu"
) -> BrainMasker:
    """Load a masker: ``"default"`` (the shipped one), a checkpoint folder or a run folder.

    Loading reads safetensors and JSON only; no code runs.

    Raises:
        CheckpointError: If the folder is missing, modified, or not a brain-mask model.
    """
    if str(path_or_name) == DEFAULT_MODEL:
        folder = brain_mask_model_path()
    else:
        folder = resolve_model_path(path_or_name)
    checkpoint = load_checkpoint(folder, device)
    if checkpoint.config.get("architecture") != _ARCHITECTURE:
        raise CheckpointError(
            folder,
            f"not a brain-mask model (architecture {checkpoint.config.get('architecture')!r}, "
            f"expected {_ARCHITECTURE!r})",
        )
    try:
        masker = BrainMasker(BrainMaskConfig.from_dict(checkpoint.config["brain_mask"]))
        masker.load_state_dict(checkpoint.state_dict)
    except (KeyError, ValueError, RuntimeError) as exc:
        raise CheckpointError(folder, f"invalid brain-mask model: {exc}") from exc
    return masker.to(device).eval()
