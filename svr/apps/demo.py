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

import json
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import cast

import torch

from svr.apps.demo_scores import (
    DemoResult,
    VolumeScore,
    score_figure,
    score_method,
)
from svr.errors import ConfigFieldError
from svr.files import atomic_directory
from svr.geometry import se3_compose, se3_inverse
from svr.image import Image
from svr.models.backbones import BackboneConfig
from svr.models.network import ModelConfig, SlicePoseNet
from svr.models.predict import load_any_pose_model, load_pose_model
from svr.models.stack_pose import STACK_POSE_MODEL, StackPoseNet
from svr.models.train import OptimConfig, TrainConfig, train
from svr.reconstruction.config import GridConfig, ReconstructionConfig
from svr.reconstruction.outputs import write_transforms, write_volume
from svr.reconstruction.pipeline import reconstruct
from svr.reconstruction.result import ReconstructionResult
from svr.reconstruction.stacks import Stack, prepare_stacks
from svr.sampling.augment import SliceAugmentConfig
from svr.sampling.dataset import SliceDatasetConfig
from svr.sampling.mirror_planes import resolve_symmetry
from svr.sampling.phantom import gestational_age_config, make_phantom, required_field_of_view_mm
from svr.sampling.simulate import SimulationConfig, simulate_case, write_case
from svr.sampling.slicer import SliceConfig
from svr.sampling.volume import CanonicalVolume, canonicalize
from svr.timing import PhaseTimer
from svr.validation import check_instance, check_instance_tuple

__all__ = [
    "DEMO_REGISTRATIONS",
    "TRAIN_MODEL",
    "DemoConfig",
    "demo_config",
    "quick_phantom",
    "run_demo",
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
        reconstructions: Settings of each reconstruction, one per ``registrations`` (for
            ``"cnn"``, the start's kind follows the model: a stack- or a slice-pose network).
        train: How a model is trained when :func:`run_demo` is asked to train one
            (``output_dir`` and ``device`` are replaced by the run's).
        registrations: The reconstructions to run, in order: ``"stack"`` and/or ``"cnn"``.

    Raises:
        ConfigFieldError: If ``registrations`` is empty, repeats one, or names an unknown one, or
            a nested configuration is not one, or ``reconstructions`` does not hold one per
            registration.
    """

    simulation: SimulationConfig
    train: TrainConfig
    reconstructions: tuple[ReconstructionConfig, ...] = field(
        default_factory=lambda: tuple(_reconstruction_config(n) for n in DEMO_REGISTRATIONS)
    )
    registrations: tuple[str, ...] = DEMO_REGISTRATIONS

    def __post_init__(self) -> None:
        owner = "DemoConfig"
        check_instance(owner, "simulation", self.simulation, SimulationConfig)
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
        configs = check_instance_tuple(
            owner, "reconstructions", self.reconstructions, ReconstructionConfig, allow_list=True
        )
        if len(configs) != len(regs):
            raise ConfigFieldError(
                owner, "reconstructions", f"one per registration ({len(regs)})", configs
            )
        object.__setattr__(self, "reconstructions", configs)


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
    size, spacing, width, depth, batch, steps = 64, 2.0, 16, 4, 32, 2000
    if quick:
        simulation = replace(simulation, in_plane_mm=_QUICK_SPACING_MM, margin_mm=4.0)
        size, spacing, width, depth, batch, steps = 32, 3.2, 8, 3, 8, 10
    reconstructions = tuple(_reconstruction_config(name, quick, seed) for name in registrations)
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
    return DemoConfig(
        simulation=simulation,
        train=training,
        reconstructions=reconstructions,
        registrations=tuple(registrations),
    )


def _reconstruction_config(
    registration: str, quick: bool = False, seed: int = 0
) -> ReconstructionConfig:
    """The library's defaults for a demo registration's start, or the quick run's settings.

    ``"cnn"`` is the learned start; the quick run is 2 mm, 2 rounds and few steps.
    """
    kind = "learned" if registration == "cnn" else "stack"
    config = replace(ReconstructionConfig.preset(kind), seed=seed)
    if not quick:
        return config
    return replace(
        config,
        grid=GridConfig(resolution_mm=_QUICK_SPACING_MM),
        schedule=replace(
            config.schedule,
            rounds=2,
            svr_levels=2,
            svr_iterations=3,
            group_sizes=(2,),
            min_slice_pixels=50,
        ),
        superres=replace(config.superres, iterations=(3, 5)),
    )


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


def _reconstruct(
    stacks: list[Stack],
    settings: ReconstructionConfig,
    model: SlicePoseNet | StackPoseNet | None,
    folder: Path,
    device: str,
    progress: bool,
) -> tuple[ReconstructionResult, float]:
    """One reconstruction (a learned start of the model's kind), its files written in ``folder``."""
    start = time.perf_counter()
    if model is not None:
        kind = "learned" if isinstance(model, StackPoseNet) else "learned-slices"
        settings = replace(settings, initialisation=replace(settings.initialisation, kind=kind))
    result = reconstruct(stacks, settings, model=model, device=device, progress=progress)
    seconds = time.perf_counter() - start
    folder.mkdir()
    write_volume(result.volume, folder / "volume.nii.gz")
    write_volume(result.initial_volume, folder / "initial.nii.gz")
    write_transforms(result, folder / "transforms.csv")
    return result, seconds


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
    steps = PhaseTimer(steps=use_cnn + 1 + len(config.registrations) + 1, logger=log)
    train_config = replace(config.train, device=device)
    with atomic_directory(output_dir, overwrite) as tmp:
        pose_model, model_name = None, None
        if use_cnn:
            with steps.phase("model", "pose model"):
                pose_model, model_name = _obtain_model(model, train_config, volume, tmp, progress)
        with steps.phase("simulation", f"simulating stacks from {source}"):
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
        for registration, settings in zip(
            config.registrations, config.reconstructions, strict=True
        ):
            name = f"reconstruction ({registration})"
            with steps.phase(name, f"reconstruction with {registration} registration"):
                model_used = pose_model if registration == "cnn" else None
                result, seconds = _reconstruct(
                    stacks, settings, model_used, tmp / registration, device, progress
                )
                method, method_rows = score_method(
                    registration, result, true_poses, scanner_from_canonical, truth, mask, seconds
                )
            methods.append(method)
            rows += method_rows
        with steps.phase("outputs", "scores, figure and metrics"):
            write_volume(truth, tmp / "ground_truth.nii.gz")
            score_figure(truth, mask, rows, tmp / "figure.png")
        summary = DemoResult(Path(output_dir), source, model_name, methods, steps.timings)
        payload = {
            **summary.to_dict(),
            "device": device,
            "config": {
                "simulation": asdict(config.simulation),
                "reconstruction": {
                    name: asdict(settings)
                    for name, settings in zip(
                        config.registrations, config.reconstructions, strict=True
                    )
                },
                "train": train_config.to_dict() if use_cnn and model == TRAIN_MODEL else None,
            },
        }
        (tmp / "metrics.json").write_text(json.dumps(payload, indent=1) + "\n")
    return summary
