"""The demo's scores: a reconstruction against the ground truth it was simulated from.

A reconstruction is defined up to one rigid transform of its frame, found from the slices' poses
(:func:`frame_alignment`); the volume is then scored inside the brain after a linear intensity fit
(:func:`score_volume`: CC, PSNR, SSIM), and every slice's pose against its truth.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import cast

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from torch import Tensor

from svr.geometry import se3_compose, se3_inverse, se3_to_vector, so3_log
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, resample_to_grid
from svr.image_metrics import ncc, psnr, ssim
from svr.metrics import pose_errors
from svr.reconstruction.qa import orthogonal_planes
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.slices import SliceSet, plane_poses

__all__ = [
    "DemoResult",
    "MethodResult",
    "VolumeScore",
    "frame_alignment",
    "score_figure",
    "score_method",
    "score_volume",
]


@dataclass(frozen=True)
class VolumeScore:
    """Agreement of a volume with the ground truth (see the module docstring)."""

    cc: float
    psnr_db: float
    ssim: float


@dataclass(frozen=True)
class MethodResult:
    """One reconstruction and its scores.

    Attributes:
        registration: ``"stack"`` or ``"cnn"``.
        frame: The frame of its volume, ``"scanner"`` or ``"canonical"``.
        initialisation: Per stack, the initialisation the pipeline kept.
        initial: Scores of the initial volume.
        reconstructed: Scores of the reconstruction.
        frame_offset_deg: Angle of the frame offset (degrees).
        frame_offset_mm: How far the frame offset moves the brain's centre (mm).
        slice_rotation_error_deg: Median rotation error of the final slice poses (degrees).
        slice_translation_error_mm: Median distance of the final slice centres from the true ones.
        seconds: Wall time of the reconstruction.
        rounds: Rounds the reconstruction ran (the first volume and the final one included).
        converged: Whether its slices stopped moving before the cap on rounds (``None``:
            no verdict, as for the fixed schedule or the quick demo's two rounds).
    """

    registration: str
    frame: str
    initialisation: tuple[str, ...]
    initial: VolumeScore
    reconstructed: VolumeScore
    frame_offset_deg: float
    frame_offset_mm: float
    slice_rotation_error_deg: float
    slice_translation_error_mm: float
    seconds: float
    rounds: int = 0
    converged: bool | None = None


@dataclass(frozen=True)
class DemoResult:
    """What :func:`run_demo` did.

    Attributes:
        output_dir: The folder written.
        source: The name of the brain volume.
        model: The slice-pose model used (a path relative to ``output_dir`` when trained here),
            or ``None`` without ``"cnn"``.
        methods: One result per registration, in the order run.
        timings_s: Wall time of each step (s).
    """

    output_dir: Path
    source: str
    model: str | None
    methods: list[MethodResult]
    timings_s: dict[str, float] = field(default_factory=dict)

    def to_dict(self) -> dict:
        """A JSON-serialisable summary."""
        return {
            "output_dir": str(self.output_dir),
            "source": self.source,
            "model": self.model,
            "results": [asdict(m) for m in self.methods],
            "timings_s": self.timings_s,
            "total_s": sum(self.timings_s.values()),
        }


def _true_plane_poses(slices: SliceSet, true_poses: Sequence[Tensor]) -> Tensor:
    """(N, 4, 4) true pose of each slice's k-plane, ``true_poses[stack][k]``, for every slice."""
    rows = [
        true_poses[int(sid)][int(k)]
        for sid, k in zip(slices.stack_ids.cpu(), slices.slice_indices.cpu(), strict=True)
    ]
    return torch.stack(rows).to(torch.float64)


def frame_alignment(slices: SliceSet, true_poses: Sequence[Tensor]) -> Tensor:
    """The rigid transform from a reconstruction's frame to the truth's, from its slices.

    Args:
        slices: The slices with their final poses (``ReconstructionResult.slices``).
        true_poses: Per stack, in the order of ``slices.stack_names``, (K, 4, 4) true poses of
            the stack's k-planes (origin at the plane centre) in the truth's frame.

    Returns:
        (4, 4) float64 ``G``, the robust mean
        (:func:`~svr.geometry.averaging.robust_mean_pose`) of ``T_true o T_final^-1`` over the
        slices: a point ``x`` of the reconstruction's frame is at ``G x`` in the truth's.
    """
    truth = _true_plane_poses(slices, true_poses)
    final = plane_poses(slices).cpu()
    return robust_mean_pose(se3_compose(truth, se3_inverse(final)))


def score_volume(volume: Image, truth: Image, mask: Tensor) -> tuple[VolumeScore, Image]:
    """Score a volume against the ground truth (see the module docstring).

    Args:
        volume: The volume, in the truth's frame (aligned already).
        truth: The ground truth.
        mask: (I, J, K) bool brain mask on the truth's grid.

    Returns:
        The scores, and the volume on the truth's grid with its intensities fitted (zero
        outside the mask).

    Raises:
        ValueError: If the mask is empty.
    """
    inside = mask.cpu().bool()
    if not bool(inside.any()):
        raise ValueError("score_volume(): the mask is empty")
    truth = truth.to("cpu", torch.float32)
    on_grid = resample_to_grid(volume.to("cpu", torch.float32), truth).data
    x, y = on_grid[inside].double(), truth.data[inside].double()
    design = torch.stack([x, torch.ones_like(x)], dim=1)
    a, b = torch.linalg.lstsq(design, y[:, None]).solution.flatten().tolist()
    fitted = torch.where(inside, on_grid.double() * a + b, 0.0).float()
    span = float(y.max() - y.min()) or 1.0
    reference = torch.where(inside, truth.data, 0.0)
    cc = float(ncc(x[None, None], y[None, None]))
    peak = float(psnr(fitted[inside][None, None], reference[inside][None, None], span))
    lo = inside.nonzero().amin(dim=0).tolist()
    hi = (inside.nonzero().amax(dim=0) + 1).tolist()
    box = tuple(slice(s, e) for s, e in zip(lo, hi, strict=True))
    similarity = [
        float(
            ssim(
                fitted[box].movedim(axis, 0).contiguous(),
                reference[box].movedim(axis, 0).contiguous(),
                span,
            ).mean()
        )
        for axis in range(3)
    ]
    score = VolumeScore(cc=cc, psnr_db=peak, ssim=float(np.mean(similarity)))
    return score, Image(fitted, truth.affine.clone())


def _offset(transform: Tensor, centre: Tensor) -> tuple[float, float]:
    """Angle (degrees) of a rigid transform and how far it moves ``centre`` (mm)."""
    angle = math.degrees(float(so3_log(transform[:3, :3]).norm()))
    moved = transform[:3, :3] @ centre + transform[:3, 3]
    return angle, float((moved - centre).norm())


def score_figure(
    truth: Image, mask: Tensor, rows: list[tuple[str, Image, VolumeScore | None]], path: Path
) -> None:
    """Orthogonal views through the mask's centroid, one row per volume, on the truth's scale."""
    inside = mask.cpu().bool()
    centre = cast(
        "tuple[int, int, int]",
        tuple(round(float(c)) for c in inside.nonzero().double().mean(dim=0)),
    )
    world = truth.affine[:3, :3] @ torch.tensor(centre, dtype=torch.float64) + truth.affine[:3, 3]
    vmax = float(np.percentile(truth.data[inside].numpy(), 99.5)) or 1.0
    figure = Figure(figsize=(8.27, 2.5 * len(rows) + 0.4), layout="constrained")
    FigureCanvasAgg(figure)
    grid = figure.add_gridspec(len(rows), 3)
    for r, (name, image, score) in enumerate(rows):
        label = name
        if score is not None:
            label += f"\nCC {score.cc:.3f}  PSNR {score.psnr_db:.1f} dB\nSSIM {score.ssim:.3f}"
        for c, plane in enumerate(orthogonal_planes(image.data.cpu().float().numpy(), centre)):
            ax = figure.add_subplot(grid[r, c])
            ax.imshow(plane, cmap="gray", origin="lower", vmin=0.0, vmax=vmax)
            ax.set_xticks([])
            ax.set_yticks([])
            if c == 0:
                ax.set_ylabel(label, fontsize=8)
            if r == 0:
                axis = "xyz"[c]
                ax.set_title(f"{axis} = {float(world[c]):.1f} mm (canonical)", fontsize=9)
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", dpi=90)
    path.write_bytes(buffer.getvalue())


def score_method(
    registration: str,
    result: ReconstructionResult,
    true_poses: Sequence[Tensor],
    scanner_from_canonical: Tensor,
    truth: Image,
    mask: Tensor,
    seconds: float,
) -> tuple[MethodResult, list[tuple[str, Image, VolumeScore | None]]]:
    """Scores of one reconstruction, and its aligned, fitted volumes for the figure."""
    G = frame_alignment(result.slices, true_poses)
    if result.slices.frame == "scanner":  # the frame offset is against the frame claimed
        offset, centre = se3_compose(scanner_from_canonical, G), scanner_from_canonical[:3, 3]
    else:
        offset, centre = G, torch.zeros(3, dtype=torch.float64)
    deg, mm = _offset(offset, centre)
    aligned = se3_compose(G, plane_poses(result.slices).cpu())
    truth_poses = _true_plane_poses(result.slices, true_poses)
    errors = pose_errors(se3_to_vector(aligned), se3_to_vector(truth_poses))
    scores: dict[str, VolumeScore] = {}
    rows: list[tuple[str, Image, VolumeScore | None]] = []
    for kind, image in (("initial", result.initial_volume), ("reconstructed", result.volume)):
        moved = Image(image.data.cpu(), G @ image.affine.cpu().double())
        scores[kind], fitted = score_volume(moved, truth, mask)
        rows.append((f"{registration}: {kind}", fitted, scores[kind]))
    method = MethodResult(
        registration=registration,
        frame=result.slices.frame,
        initialisation=result.initialisation,
        initial=scores["initial"],
        reconstructed=scores["reconstructed"],
        frame_offset_deg=deg,
        frame_offset_mm=mm,
        slice_rotation_error_deg=float(errors["rotation_deg"].median()),
        slice_translation_error_mm=float(errors["translation_mm"].median()),
        seconds=seconds,
        rounds=len(result.rounds),
        converged=result.converged,
    )
    return method, rows
