"""One reconstruction from files: masks, preparation, the pose model and atlases, the pipeline.

:func:`run_reconstruction` is the one path from a :class:`ReconstructionJob` (files, resolved
options) to a result, shared by ``svr reconstruct``, ``svr register`` and each participant of
``svr bids``, so that they give identical volumes for the same stacks. :func:`provenance` records
the job (every option with its value), and :func:`excluded_by_stack` the slices left out.
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass, field
from typing import Any

from svr.masking.config import MaskingConfig
from svr.options import option_values
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.stacks import Stack, StackConfig

__all__ = ["ReconstructionJob", "excluded_by_stack", "provenance", "run_reconstruction"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class ReconstructionJob:
    """What one reconstruction reads and how it runs (picklable: a worker process takes it).

    Attributes:
        stacks: The stacks (NIfTI paths).
        masks: One brain mask per stack (NIfTI paths), or ``None`` for automatic masks.
        thicknesses: Slice thickness (mm): one for all stacks, one per stack, or ``None`` for
            each stack's slice spacing (with a warning).
        config: The reconstruction; ``config.initialisation.kind`` names the start.
        model: The pose model of a learned start (a name such as ``"stack-pose"`` or a checkpoint
            folder); ``None`` for the other starts.
        atlases: ``(volume, mask)`` NIfTI paths of the atlases, the preferred first.
        masking: How stacks given without masks get them.
        preparation: How stacks are prepared.
        mask_model: The brain-mask networks (``"default"`` or a folder).
        device: Torch device.
        progress: Show progress bars.
    """

    stacks: tuple[str, ...]
    masks: tuple[str, ...] | None
    thicknesses: tuple[float, ...] | None
    config: ReconstructionConfig
    model: str | None = None
    atlases: tuple[tuple[str, str], ...] = ()
    masking: MaskingConfig = field(default_factory=MaskingConfig)
    preparation: StackConfig = field(default_factory=StackConfig)
    mask_model: str = "default"
    device: str = "cpu"
    progress: bool = True

    @property
    def mask_source(self) -> str:
        """Where the brain masks come from, for the log and the QA page."""
        if self.masks is not None:
            return "given"
        if self.masking.method == "network":
            fused = ", fused across stacks" if self.masking.fuse else ""
            return f"automatic (network, --mask-model {self.mask_model}{fused})"
        return "automatic (otsu)"


def _load_model(job: ReconstructionJob) -> Any:
    """The network of the job's learned start, checked against the start's kind."""
    from svr.models.predict import load_any_pose_model
    from svr.models.stack_pose import StackPoseNet

    kind = job.config.initialisation.kind
    if kind not in ("learned", "learned-slices"):
        return None
    if job.model is None:
        raise ValueError(f"the {kind!r} start needs a pose model; the job names none")
    model = load_any_pose_model(job.model, job.device)
    if isinstance(model, StackPoseNet) != (kind == "learned"):
        expected = "a stack-pose" if kind == "learned" else "a slice-pose"
        raise ValueError(f"model {job.model}: the {kind!r} start needs {expected} model")
    return model


def _load_stacks(job: ReconstructionJob) -> list[Stack]:
    """The prepared stacks: given masks, or the masking stage first."""
    from svr.image import load_nifti
    from svr.masking import auto_masks
    from svr.reconstruction.stacks import load_stacks, prepare_stacks, slice_thicknesses

    widths = None if job.thicknesses is None else list(job.thicknesses)
    if job.masks is not None:
        return load_stacks(list(job.stacks), list(job.masks), widths, job.preparation)
    names = list(job.stacks)
    images = [load_nifti(path) for path in job.stacks]
    if job.masking.fuse:
        widths = slice_thicknesses(widths, images, names)  # warned about once, here
    masks = auto_masks(images, job.masking, names, widths, job.mask_model, job.device)
    return prepare_stacks(images, masks, widths, job.preparation, names=names)


def run_reconstruction(job: ReconstructionJob) -> tuple[list[Stack], ReconstructionResult]:
    """Load what the job names and reconstruct.

    Args:
        job: The files and settings.

    Returns:
        The prepared stacks and the reconstruction.

    Raises:
        ValueError, OSError: For unusable files, a mask count that is not one per stack, or a
            model missing or of the wrong kind, naming the file.
    """
    if job.masks is not None and len(job.masks) != len(job.stacks):
        raise ValueError(f"got {len(job.masks)} masks for {len(job.stacks)} stacks")
    from svr.reconstruction.pipeline import reconstruct
    from svr.sampling.volume import load_canonical_volume

    model = _load_model(job)
    atlases = [load_canonical_volume(volume, mask) for volume, mask in job.atlases]
    stacks = _load_stacks(job)
    result = reconstruct(
        stacks, job.config, model=model, atlases=atlases, device=job.device, progress=job.progress
    )
    return stacks, result


def excluded_by_stack(result: ReconstructionResult) -> dict[str, list[int]]:
    """Stack name -> k indices (in its file) of the excluded slices, for stacks that have some."""
    slices = result.slices
    out: dict[str, list[int]] = {}
    for row in result.excluded.nonzero().flatten().tolist():
        name = slices.stack_names[int(slices.stack_ids[row])]
        out.setdefault(name, []).append(int(slices.slice_indices[row]))
    return out


def provenance(job: ReconstructionJob) -> dict[str, Any]:
    """Every setting of the job, for a log or a sidecar: the options with their values.

    Returns:
        ``{"start", "model", "atlases", "options", "masks", "masking", "stack_preparation",
        "reconstruction", "device"}``: the start's kind, the model and atlases, every
        command-line option of the configuration with its value, where the masks come from,
        the masking and preparation settings, and every field of the configuration.
    """
    return {
        "start": job.config.initialisation.kind,
        "model": job.model,
        "atlases": [list(pair) for pair in job.atlases],
        "options": option_values(job.config),
        "masks": job.mask_source,
        "masking": None if job.masks is not None else dataclasses.asdict(job.masking),
        "stack_preparation": dataclasses.asdict(job.preparation),
        "reconstruction": job.config.settings(),
        "device": job.device,
    }
