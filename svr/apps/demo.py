"""The main job of ``svr demo``: simulate stacks from a brain, pose the slices, reconstruct, score.

:func:`run_demo` runs the whole toolkit on one case whose truth is known:

1. **Pose model** (``"cnn"`` only): by default the shipped stack-pose model
   (:mod:`svr.models.stack_pose`: each stack placed in canonical space from its own data, never
   trained on the volume); or a given model; or (:data:`TRAIN_MODEL`) a small SE(3) slice-pose
   model trained here on the volume (:func:`svr.models.train.train`), which has seen the very
   anatomy it is tested on (in-distribution): that shows the pipeline at work, not how a model
   generalises to new brains.
2. **Simulate** motion-corrupted thick-slice stacks from the volume
   (:func:`svr.sampling.simulate.simulate_case`; ``svr demo`` uses the built-in phantom by
   default): three 3 mm stacks planned along the brain's axes (axial, coronal, sagittal, as
   radiographers plan fetal stacks; no random placement), random-walk motion of a few degrees
   and millimetres during the scan, and Rician noise.
3. **Reconstruct** with each registration (:func:`svr.reconstruction.pipeline.reconstruct`):
   ``"stack"`` (the volume in the scanner frame) and ``"cnn"`` (in canonical space), from the
   simulated stacks and their brain masks.
4. **Score** the initial volume (the scattered-data approximation at the initial poses) and the
   reconstruction against the ground truth (:func:`score_volume`).

Scoring. A reconstruction is defined up to one rigid transform of its frame: stack registration
keeps the template stack where the scanner saw it, although the fetus moved while it was
acquired, and the CNN puts the brain where the model believes canonical space is. The simulation
knows every slice's true pose, so :func:`frame_alignment` estimates that transform from the
slices (the robust mean of ``T_true o T_final^-1``); it is reported as the *frame offset* (its
angle, and how far it moves the brain's centre, against the frame the volume claims to be in)
and removed. Every volume is then resampled by world position (trilinear) onto the grid of the
ground truth in canonical space, its intensities inside the truth's brain mask are fitted to the
truth's by least squares (``a x + b``: a reconstruction has the stacks' intensity unit), and

* **CC**: Pearson correlation over the mask's voxels (:func:`svr.image_metrics.ncc`; the fit
  does not change it);
* **PSNR**: over the mask's voxels, with the truth's in-mask intensity span as the data range
  (:func:`svr.image_metrics.psnr`);
* **SSIM**: :func:`svr.image_metrics.ssim` of the planes of the mask's bounding box along each
  of the three grid axes (zero outside the mask), averaged over the planes and the axes.

The median rotation and translation errors of the final slice poses, after the frame alignment,
are reported as well.

Outputs (one folder, written atomically; nothing is left behind on an error):

* ``case/``: the simulated case in the layout of ``svr simulate`` (stacks, masks, ground truth
  in the scanner frame, ``truth_slices.json``);
* ``model/``: the trained slice-pose model (when one was trained), loadable with ``--model
  model/checkpoints/step_NNNNNNNNN``;
* ``ground_truth.nii.gz``: the ground truth in canonical space, the reference of every score;
* ``<registration>/volume.nii.gz``, ``initial.nii.gz``, ``transforms.csv``: each
  reconstruction, its initial volume (in the reconstruction's own frame) and the final slice
  poses;
* ``metrics.json``: the scores, frame offsets, pose errors, timings and settings;
* ``figure.png``: orthogonal views of the ground truth and of each initial and reconstructed
  volume (aligned and intensity-fitted as scored), with their scores.
"""

from __future__ import annotations

import io
import json
import logging
import math
import os
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import cast

import numpy as np
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from torch import Tensor

from svr.errors import ConfigFieldError
from svr.files import atomic_directory
from svr.geometry import se3_compose, se3_inverse, se3_to_vector, so3_log
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, resample_to_grid
from svr.image_metrics import ncc, psnr, ssim
from svr.metrics import pose_errors
from svr.models.backbones import BackboneConfig
from svr.models.network import ModelConfig, SlicePoseNet
from svr.models.predict import load_any_pose_model, load_pose_model
from svr.models.stack_pose import STACK_POSE_MODEL, StackPoseNet
from svr.models.train import OptimConfig, TrainConfig, train
from svr.reconstruction.config import ReconstructionConfig, ReconstructionResult
from svr.reconstruction.outputs import write_transforms, write_volume
from svr.reconstruction.pipeline import reconstruct
from svr.reconstruction.qa import orthogonal_planes
from svr.reconstruction.slices import SliceSet, plane_poses
from svr.reconstruction.stacks import prepare_stacks
from svr.sampling.augment import SliceAugmentConfig
from svr.sampling.dataset import SliceDatasetConfig
from svr.sampling.mirror_planes import resolve_symmetry
from svr.sampling.phantom import gestational_age_config, make_phantom, required_field_of_view_mm
from svr.sampling.simulate import SimulationConfig, simulate_case, write_case
from svr.sampling.slicer import SliceConfig
from svr.sampling.volume import CanonicalVolume, canonicalize
from svr.validation import check_instance, check_instance_tuple

__all__ = [
    "DEMO_REGISTRATIONS",
    "TRAIN_MODEL",
    "DemoConfig",
    "DemoResult",
    "MethodResult",
    "VolumeScore",
    "demo_config",
    "frame_alignment",
    "quick_phantom",
    "run_demo",
    "score_volume",
]

log = logging.getLogger(__name__)

DEMO_REGISTRATIONS = ("stack", "cnn")
TRAIN_MODEL = "train"
"""The model argument of :func:`run_demo` that asks for a model trained on the demo's volume."""

_QUICK_SPACING_MM = 2.0  # voxel size of the quick phantom and of everything quick mode computes


@dataclass(frozen=True)
class DemoConfig:
    """What :func:`run_demo` simulates, trains and reconstructs.

    Attributes:
        simulation: The stacks simulated from the volume.
        reconstruction: Settings of every reconstruction; its ``registration`` is replaced by
            each of ``registrations`` in turn.
        train: How a model is trained when :func:`run_demo` is asked to train one
            (``output_dir`` and ``device`` are replaced by the run's).
        registrations: The reconstructions to run, in order: ``"stack"`` and/or ``"cnn"``.

    Raises:
        ConfigFieldError: If ``registrations`` is empty, repeats one, or names an unknown one, or
            a nested configuration is not one.
    """

    simulation: SimulationConfig
    reconstruction: ReconstructionConfig
    train: TrainConfig
    registrations: tuple[str, ...] = DEMO_REGISTRATIONS

    def __post_init__(self) -> None:
        owner = "DemoConfig"
        check_instance(owner, "simulation", self.simulation, SimulationConfig)
        check_instance(owner, "reconstruction", self.reconstruction, ReconstructionConfig)
        check_instance(owner, "train", self.train, TrainConfig)
        regs = check_instance_tuple(
            owner, "registrations", self.registrations, str, allow_list=True
        )
        if not regs or len(set(regs)) != len(regs) or not set(regs) <= set(DEMO_REGISTRATIONS):
            listed = ", ".join(repr(name) for name in DEMO_REGISTRATIONS)
            raise ConfigFieldError(
                owner, "registrations", f"distinct values of {listed}", self.registrations
            )
        object.__setattr__(self, "registrations", regs)


def demo_config(
    quick: bool = False,
    seed: int = 0,
    train_steps: int | None = None,
    registrations: Sequence[str] = DEMO_REGISTRATIONS,
) -> DemoConfig:
    """The demo's settings: the full run (minutes on a CPU) or a quick one (seconds, for tests).

    Full: three orthogonal 3 mm stacks at 1 mm in-plane along the brain's axes (no random
    placement), random-walk motion (5° and 2 mm per axis at the end of the scan), noise 2 %; a
    ResNet (width 16, 4 stages) on 64 x 64 slices at 2 mm, trained for 2000 steps of 32 slices
    at random poses in the paper's Euler box (angles in ±90°, offsets in ±40 mm; thickness 2 to
    4 mm, in-plane shifts up to 6 mm, intensity augmentation); reconstruction with the
    library's defaults (0.8 mm, 5 rounds). Quick: the same at 2 mm, a tiny model trained for
    10 steps of 8 slices, and 2 rounds with few iterations.

    Args:
        quick: The quick variant (use it with :func:`quick_phantom`).
        seed: Seed of the simulation, the training and the reconstructions.
        train_steps: Training steps (default: 2000, or 10 when quick).
        registrations: The reconstructions to run.

    Returns:
        The configuration.
    """
    simulation = SimulationConfig(random_placement=False, seed=seed)
    reconstruction = ReconstructionConfig(seed=seed)
    size, spacing, width, depth, batch, steps = 64, 2.0, 16, 4, 32, 2000
    if quick:
        simulation = replace(simulation, in_plane_mm=_QUICK_SPACING_MM, margin_mm=4.0)
        reconstruction = replace(
            reconstruction,
            output_resolution_mm=_QUICK_SPACING_MM,
            outer_iterations=2,
            sr_iterations=(3, 5),
            svr_levels=2,
            svr_iterations=3,
            group_sizes=(2,),
            min_slice_pixels=50,
        )
        size, spacing, width, depth, batch, steps = 32, 3.2, 8, 3, 8, 10
    steps = steps if train_steps is None else train_steps
    model = ModelConfig(
        backbone=BackboneConfig(name="resnet", width=width, depth=depth),
        representation="se3",
        input_size=(size, size),
        spacing_mm=spacing,
    )
    training = TrainConfig(
        output_dir="model",
        model=model,
        data=SliceDatasetConfig(
            slice=SliceConfig(size=(size, size), spacing_mm=spacing),
            thickness_range_mm=(2.0, 4.0),
            rotation="euler",
            shift_mm=6.0,
            representation="se3",
            augment=SliceAugmentConfig(),
            batch_size=batch,
            seed=seed,
        ),
        optim=OptimConfig(lr=2e-3, warmup_steps=min(50, steps // 10)),
        steps=steps,
        checkpoint_every=steps,
        keep_checkpoints=1,
        log_every=max(1, min(20, steps)),
        seed=seed,
    )
    return DemoConfig(simulation, reconstruction, training, tuple(registrations))


def quick_phantom(weeks: float = 28.0) -> tuple[CanonicalVolume, str]:
    """The built-in phantom at 2 mm on the smallest grid that holds it, for the quick demo.

    Args:
        weeks: Gestational age in [20, 38] (:func:`svr.sampling.phantom.gestational_age_config`).

    Returns:
        The phantom in canonical space, and a name for it.
    """
    config = gestational_age_config(weeks, spacing_mm=_QUICK_SPACING_MM)
    fov = required_field_of_view_mm(config.brain_length_mm, _QUICK_SPACING_MM)
    shape = cast("tuple[int, int, int]", tuple(math.ceil(mm / _QUICK_SPACING_MM) + 1 for mm in fov))
    volume, mask = make_phantom(replace(config, shape=shape))
    name = f"phantom (GA {weeks:g} weeks, {_QUICK_SPACING_MM:g} mm)"
    return canonicalize(volume, mask, name="phantom"), name


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


def _figure(
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


def _obtain_model(
    model: str, config: TrainConfig, volume: CanonicalVolume, folder: Path, progress: bool
) -> tuple[SlicePoseNet | StackPoseNet, str]:
    """Train a model in ``folder / "model"`` or load the given one; returns it and its name."""
    if model != TRAIN_MODEL:
        log.info("loading the pose model %s", model)
        return load_any_pose_model(model, config.device), model
    run = replace(config, output_dir=str(folder / "model"))
    if not run.model.symmetry_planes:
        planes, report = resolve_symmetry("auto", [volume], ["demo volume"])
        run = replace(run, model=replace(run.model, symmetry_planes=planes), symmetry_report=report)
    log.info("training a slice-pose model on the volume (%d steps)", run.steps)
    result = train(run, [volume], resume=False, overwrite=True, progress=progress)
    log.info("last training loss %.4g", result.last_loss)
    name = str(result.checkpoint.relative_to(folder))
    return load_pose_model(result.checkpoint, config.device), name


def _score(
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


class _Steps:
    """Numbered progress messages, ``[i/n] what``, and the wall time of each step."""

    def __init__(self, count: int) -> None:
        self.count, self.done = count, 0
        self.timings: dict[str, float] = {}

    @contextmanager
    def step(self, name: str, message: str, *args: object) -> Iterator[None]:
        self.done += 1
        log.info("[%d/%d] %s", self.done, self.count, message % args)
        start = time.perf_counter()
        yield
        self.timings[name] = self.timings.get(name, 0.0) + time.perf_counter() - start


def run_demo(
    volume: CanonicalVolume,
    config: DemoConfig,
    output_dir: str | os.PathLike[str],
    *,
    model: str = STACK_POSE_MODEL,
    source: str = "volume",
    device: str = "cpu",
    overwrite: bool = False,
    progress: bool = True,
) -> DemoResult:
    """Simulate, pose, reconstruct and score (see the module docstring); write the outputs.

    Args:
        volume: The brain (ground truth), e.g. :func:`quick_phantom` or
            :func:`svr.sampling.volume.load_canonical_volume`.
        config: The settings (:func:`demo_config`).
        output_dir: The folder to create.
        model: For ``"cnn"``: ``"stack-pose"`` (the shipped stack-pose model, the default),
            ``"default"`` (the shipped slice-pose model), a checkpoint folder of either kind, or
            :data:`TRAIN_MODEL` (``"train"``) to train a slice-pose model on ``volume``.
        source: The volume's name for the outputs.
        device: Torch device of every step.
        overwrite: Replace an existing ``output_dir``.
        progress: Show progress bars.

    Returns:
        The scores and timings.

    Raises:
        OutputExistsError: If ``output_dir`` exists and ``overwrite`` is false (checked first).
        CheckpointError: If a given model cannot be loaded (checked before the simulation).
    """
    use_cnn = "cnn" in config.registrations
    steps = _Steps(2 + use_cnn + len(config.registrations))
    train_config = replace(config.train, device=device)
    with atomic_directory(output_dir, overwrite) as tmp:
        pose_model, model_name = None, None
        if use_cnn:
            with steps.step("model", "pose model"):
                pose_model, model_name = _obtain_model(model, train_config, volume, tmp, progress)
        with steps.step("simulation", "simulating stacks from %s", source):
            case = simulate_case(volume, config.simulation, progress=progress, device=device)
            write_case(case, tmp / "case", source=source)
            stacks = prepare_stacks(
                [s.image for s in case.stacks],
                [s.mask for s in case.stacks],
                config.simulation.thickness_mm,
                names=[f"case/stacks/stack{i}.nii.gz" for i in range(len(case.stacks))],
            )
        truth, mask = volume.image.to("cpu", torch.float32), volume.mask.cpu()
        scanner_from_canonical = case.gt_volume.affine.double() @ torch.linalg.inv(
            volume.image.affine.double()
        )
        canonical_from_scanner = se3_inverse(scanner_from_canonical)
        true_poses = [se3_compose(canonical_from_scanner, s.true_poses) for s in case.stacks]
        rows: list[tuple[str, Image, VolumeScore | None]] = [("ground truth", truth, None)]
        methods = []
        for registration in config.registrations:
            name = f"reconstruction ({registration})"
            with steps.step(name, "reconstruction with %s registration", registration):
                start = time.perf_counter()
                result = reconstruct(
                    stacks,
                    replace(config.reconstruction, registration=registration),
                    model=pose_model if registration == "cnn" else None,
                    device=device,
                    progress=progress,
                )
                seconds = time.perf_counter() - start
                folder = tmp / registration
                folder.mkdir()
                write_volume(result.volume, folder / "volume.nii.gz")
                write_volume(result.initial_volume, folder / "initial.nii.gz")
                write_transforms(result, folder / "transforms.csv")
                method, method_rows = _score(
                    registration, result, true_poses, scanner_from_canonical, truth, mask, seconds
                )
            methods.append(method)
            rows += method_rows
        write_volume(truth, tmp / "ground_truth.nii.gz")
        _figure(truth, mask, rows, tmp / "figure.png")
        summary = DemoResult(Path(output_dir), source, model_name, methods, steps.timings)
        payload = {
            **summary.to_dict(),
            "device": device,
            "config": {
                "simulation": asdict(config.simulation),
                "reconstruction": asdict(config.reconstruction),
                "train": train_config.to_dict() if use_cnn and model == TRAIN_MODEL else None,
            },
        }
        (tmp / "metrics.json").write_text(json.dumps(payload, indent=1) + "\n")
    return summary
