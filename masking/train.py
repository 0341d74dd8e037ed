"""Training the brain-mask networks on simulated whole-uterus scenes only.

No real scan is used. Each training case is an atlas brain at a random age, either inside a random
whole-uterus scene (:func:`svr.sampling.scenes.make_scene`) or alone on an empty background (as in
stacks that were cropped and masked already), cut into motion-corrupted thick-slice stacks by the
project's acquisition model (:func:`svr.sampling.simulate.simulate_case`: random orientations,
slice thickness, in-plane spacing, field of view, noise, bias field, signal voids). The stacks'
slices are resampled onto the canvases that :func:`svr.masking.segment.segment_stack` uses
(:func:`svr.masking.canvas.slices_to_canvas`), with each stack's brain mask as the target:

- ``"localiser"``: the localiser's canvas centred near the stack's middle, shifted at random
  (by up to ``StageData.centre_shift_mm``, per stack or per slice: the whole-slice canvas, or a
  tile anywhere in the field of view for the tiled recipe); all slices through the brain and
  as many without;
- ``"segmenter"``: the fine canvas centred on the brain's centroid plus a random error (as the
  localiser's), for the slices through the brain and one beyond each end (or every slice, with
  ``StageData.segment_all_slices``).

:func:`make_examples` builds them, :func:`train_network` fits one U-Net (soft Dice + binary cross
entropy, Adam, random flips, gamma, contrast and optional random intensity maps), checkpointing
and resuming (:mod:`svr.models.resume`), and ``svr train-brain-mask`` runs both stages and writes
the model.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
from torch import Tensor
from torch.nn import functional

from svr.masking.canvas import neighbour_slices, normalise_stack, slices_to_canvas
from svr.masking.config import BrainMaskConfig
from svr.models.resume import cosine_schedule, resume_training, save_training_checkpoint
from svr.models.segmentation import BrainUNet, SegmentationConfig
from svr.sampling.scenes import SceneConfig, make_scene
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import CanonicalVolume
from svr.validation import check_fraction, check_int, check_number

__all__ = [
    "BrainMaskTrainingConfig",
    "Stage",
    "StageData",
    "TrainingExamples",
    "dice_bce_loss",
    "intensity_curve",
    "make_examples",
    "stage_data",
    "train_network",
]

Stage = Literal["localiser", "segmenter"]
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class BrainMaskTrainingConfig:
    """How one network of the masker is trained.

    Attributes:
        cases: Number of simulated cases (each 2 or 3 stacks), >= 1.
        bare_fraction: Fraction of cases with the brain alone on an empty background, in [0, 1].
        steps: Optimiser steps, >= 1.
        batch_size: Canvases per step, >= 1.
        learning_rate: Adam's learning rate (cosine decay to 5 % of it), > 0.
        checkpoint_every: Steps between checkpoints, >= 1.
        seed: Seed of the data and of the training.
        intensity_curves: Fraction of the training canvases given a random increasing
            intensity map (:func:`intensity_curve`), in [0, 1].
    """

    cases: int = 100
    bare_fraction: float = 0.25
    steps: int = 4000
    batch_size: int = 16
    learning_rate: float = 2e-3
    checkpoint_every: int = 250
    seed: int = 0
    intensity_curves: float = 0.0

    def __post_init__(self) -> None:
        owner = "BrainMaskTrainingConfig"
        for name in ("cases", "steps", "batch_size", "checkpoint_every"):
            check_int(owner, name, getattr(self, name), minimum=1)
        check_fraction(owner, "intensity_curves", self.intensity_curves)
        check_fraction(owner, "bare_fraction", self.bare_fraction)
        check_number(owner, "learning_rate", self.learning_rate, gt=0)
        check_int(owner, "seed", self.seed, minimum=0)


@dataclass
class TrainingExamples:
    """Canvases and their brain targets.

    Attributes:
        inputs: (N, C, S, S) float16 normalised canvases (C > 1: a 2.5D segmenter's slices
            with their neighbours, :func:`~svr.masking.canvas.neighbour_slices`).
        targets: (N, 1, S, S) bool brain masks on the same canvases.
    """

    inputs: Tensor
    targets: Tensor


@dataclass(frozen=True)
class StageData:
    """The scenes and acquisitions one network's examples are simulated from.

    Attributes:
        scene: The whole-uterus scenes (:func:`svr.sampling.scenes.make_scene`).
        in_plane_mm: Range of the stacks' in-plane spacing, mm.
        margin_mm: Range of the field of view beyond the brain in scenes, mm.
        bare_margin_mm: The same for bare brains, mm.
        centre_shift_mm: The localiser's canvas centres are drawn uniformly within this
            distance of the stack's middle along each in-plane axis, mm.
        shift_per_slice: Whether each localiser canvas gets its own centre (else one per stack).
        segment_all_slices: Whether the segmenter's canvases come from every slice of a stack
            (those without brain teach it to find none there), not only from the brain's
            slices and one beyond each end.
        mask_fraction: ``SimulationConfig.mask_fraction`` of the slice masks (``None``: the
            brain on each slice's centre plane).
        grazing_ratio: ``SimulationConfig.grazing_ratio`` (which slices take the
            partial-volume mask; ``None``: all).
    """

    scene: SceneConfig
    in_plane_mm: tuple[float, float]
    margin_mm: tuple[float, float]
    bare_margin_mm: tuple[float, float] = (2.0, 20.0)
    centre_shift_mm: float = 60.0
    shift_per_slice: bool = False
    segment_all_slices: bool = False
    mask_fraction: float | None = None
    grazing_ratio: float | None = None


# Shared by both networks' scenes: the head as it looks on fetal T2 stacks (a wide, bright
# extra-axial CSF space and a thin skull; thick dark skulls taught the first networks a cue that
# real stacks do not show), a large textured fetal body, intracranial masks.
_HEAD: dict[str, Any] = {
    "csf_mm": (2.0, 9.0),
    "skull_mm": (0.8, 3.0),
    "skull_intensity": (0.02, 0.5),
    "body_scale": (1.2, 2.2),
    "intracranial_mask": True,
}
# ``tight_heads``: the head as on the clinical scan's stacks, where fluid touching the head was
# taken into the mask: a narrower CSF space, a skull that may be faint and thin, and a scalp that
# may be almost absent, so that the skull's line and the head's shape, not a wide grey band,
# tell the head from the fluid around it.
_TIGHT_HEAD: dict[str, Any] = {
    **_HEAD,
    "csf_mm": (1.0, 6.0),
    "skull_mm": (0.5, 2.5),
    "skull_intensity": (0.02, 0.7),
    "scalp_mm": (0.3, 3.0),
}

# ``thick_skulls``: a variant testing whether the grey band the clinical scan's manual masks hold
# (skull and scalp blurred together by thick slices) is a thick, grey skull inside the mask with
# fluid close outside. Measured worse on the real scan (Dice 0.775-0.857: the masks shrank); kept
# to reproduce that measurement.
_THICK_SKULL: dict[str, Any] = {
    "skull_mm": (2.0, 5.0),
    "skull_intensity": (0.1, 0.7),
    "scalp_mm": (0.3, 2.0),
}

# ``partial_volume``: a thick slice's mask holds the brain wherever a fifth of its profile is
# brain, as manual masks include the slices that graze the top and bottom of the head.
PARTIAL_VOLUME_MASK_FRACTION = 0.2
# ``grazing_only``: only the slices whose centre-plane mask is under half their partial-volume
# mask take it (the top and bottom of the head); the others keep the centre-plane outline.
GRAZING_RATIO = 0.5


def stage_data(
    stage: Stage,
    tiles: bool = False,
    tight_heads: bool = False,
    faces: bool = False,
    partial_volume: bool = False,
    spinal_cord: bool = False,
    grazing_only: bool = False,
    thick_skulls: bool = False,
) -> StageData:
    """The simulation behind the shipped networks.

    Without ``tiles`` (the first recipe): coarse, wide scenes with many distracting organs for
    the localiser (its canvas has 3 mm pixels, so finer stacks would only cost time); fine
    scenes with a field of view of a few centimetres around the head for the segmenter.

    Args:
        stage: ``"localiser"`` or ``"segmenter"``.
        tiles: The recipe of the masker with a localiser on tiles
            (``BrainMaskConfig.localiser_tiles``). Localiser: finer wide scenes and stacks,
            heads that may touch the uterine wall (little or no fluid beyond them), canvas
            centres anywhere in the field of view. Segmenter: heads that may touch the wall,
            masks up to the skull's outer edge (as the manual masks of clinical stacks are
            drawn around the skull's dark rim).
        tight_heads: Heads with a narrower CSF space, fainter and thinner skulls and scalps
            down to 0.3 mm (all scenes of either stage).
        faces: Heads with a face and eyes, and bodies on a neck (``SceneConfig.face``).
        partial_volume: Slice masks that hold the brain wherever a fifth of the slice's
            profile is brain (``StageData.mask_fraction`` 0.2), not only on its centre plane.
        spinal_cord: Heads that end at the skull base, the brainstem below it being the
            spinal cord (``SceneConfig.spinal_cord``).
        grazing_only: With ``partial_volume``, only the slices whose centre-plane mask is
            under half their partial-volume mask take it (``StageData.grazing_ratio`` 0.5):
            the slices grazing the head's top and bottom; the others keep the centre plane's.
        thick_skulls: Skulls of 2-5 mm that may be grey (intensity 0.1-0.7) under a scalp of
            0.3-2 mm, so that fluid may nearly touch them (all scenes of either stage; with
            ``tiles`` the segmenter's masks hold the skull).

    Raises:
        ValueError: If ``grazing_only`` is given without ``partial_volume``, or
            ``thick_skulls`` with ``tight_heads``.
    """
    if grazing_only and not partial_volume:
        raise ValueError("stage_data(): 'grazing_only' needs 'partial_volume'")
    if thick_skulls and tight_heads:
        raise ValueError("stage_data(): 'thick_skulls' and 'tight_heads' exclude each other")
    head = {
        **(_TIGHT_HEAD if tight_heads else _HEAD),
        **(_THICK_SKULL if thick_skulls else {}),
        "face": faces,
        "spinal_cord": spinal_cord,
    }
    fraction = PARTIAL_VOLUME_MASK_FRACTION if partial_volume else None
    ratio = GRAZING_RATIO if grazing_only else None
    if stage == "localiser":
        scene = SceneConfig(
            extent_mm=320.0 if tiles else 400.0,
            spacing_mm=1.6 if tiles else 2.5,
            fluid_margin_mm=(0.5, 30.0) if tiles else (3.0, 30.0),
            distractors=(30, 80),
            distractor_mm=(3.0, 25.0),
            **head,
        )
        if tiles:
            return StageData(
                scene,
                (1.0, 1.8),
                (40.0, 130.0),
                centre_shift_mm=120.0,
                shift_per_slice=True,
                mask_fraction=fraction,
                grazing_ratio=ratio,
            )
        return StageData(
            scene, (1.5, 2.5), (40.0, 130.0), mask_fraction=fraction, grazing_ratio=ratio
        )
    scene = SceneConfig(
        extent_mm=200.0,
        spacing_mm=1.25,
        fluid_margin_mm=(0.5, 40.0) if tiles else (5.0, 40.0),
        abdomen_margin_mm=(10.0, 60.0),
        distractors=(10, 30),
        distractor_mm=(3.0, 20.0),
        skull_in_mask=tiles,
        **head,
    )
    return StageData(scene, (0.8, 1.5), (30.0, 50.0), mask_fraction=fraction, grazing_ratio=ratio)


def _case_simulation(
    data: StageData, bare: bool, rng: np.random.Generator, seed: int
) -> SimulationConfig:
    """A random acquisition for one case."""
    thickness = float(rng.uniform(2.5, 4.5))
    margin = float(rng.uniform(*(data.bare_margin_mm if bare else data.margin_mm)))
    return SimulationConfig(
        num_stacks=int(rng.integers(2, 4)),
        thickness_mm=thickness,
        spacing_mm=thickness * float(rng.uniform(0.9, 1.1)),
        in_plane_mm=float(rng.uniform(*data.in_plane_mm)),
        margin_mm=margin,
        random_walk_rotation_deg=float(rng.uniform(0.0, 15.0)),
        random_walk_translation_mm=float(rng.uniform(0.0, 5.0)),
        noise=float(rng.uniform(0.005, 0.06)),
        bias_field=float(rng.uniform(0.0, 0.4)),
        signal_void_probability=float(rng.uniform(0.0, 0.15)),
        mask_fraction=data.mask_fraction,
        grazing_ratio=data.grazing_ratio,
        seed=seed,
    )


def make_examples(
    brains: Sequence[CanonicalVolume],
    stage: Stage,
    mask_config: BrainMaskConfig,
    config: BrainMaskTrainingConfig,
    data: StageData | None = None,
    progress: bool = False,
    tissue_labels: Sequence[Tensor] | None = None,
) -> TrainingExamples:
    """Simulated canvases and targets for one network (module docstring).

    Args:
        brains: Canonical brain volumes to draw from (e.g. the atlas ages).
        stage: ``"localiser"`` or ``"segmenter"``.
        mask_config: The canvases (sizes and pixel sizes) of the masker being trained.
        config: Number of cases, fraction of bare brains and seed.
        data: The scenes and acquisitions; ``None`` for :func:`stage_data` of ``stage`` (and
            of ``mask_config.localiser_tiles``).
        progress: Show a progress bar over cases.
        tissue_labels: Tissue labels of each brain (e.g. the atlas parcellations); when given,
            half of the scenes give the brain a random intensity per label (SynthSeg-style).

    Returns:
        The examples (CPU).

    Raises:
        ValueError: If ``brains`` is empty or ``stage`` is unknown.
    """
    from tqdm import tqdm

    if not brains:
        raise ValueError("make_examples(): 'brains' is empty")
    if stage not in ("localiser", "segmenter"):
        raise ValueError(f"make_examples(): 'stage' must be localiser or segmenter, got {stage!r}")
    if data is None:
        data = stage_data(stage, tiles=mask_config.localiser_tiles)
    rng = np.random.default_rng([config.seed, 0 if stage == "localiser" else 1])
    size = mask_config.localiser_size if stage == "localiser" else mask_config.segmenter_size
    pixel = mask_config.localiser_mm if stage == "localiser" else mask_config.segmenter_mm
    inputs, targets = [], []
    for case in tqdm(range(config.cases), desc=f"{stage} cases", disable=not progress):
        which = int(rng.integers(len(brains)))
        brain = brains[which]
        bare = bool(rng.random() < config.bare_fraction)
        seed = int(rng.integers(2**31))
        tissue = None
        if tissue_labels is not None and rng.random() < 0.5:  # (no draw without labels)
            tissue = tissue_labels[which]
        scene = brain if bare else make_scene(brain, data.scene, seed=seed, tissue_labels=tissue)
        simulated = simulate_case(scene, _case_simulation(data, bare, rng, seed))
        for stack in simulated.stacks:
            image = normalise_stack(stack.image.data, f"case {case}")
            mask = stack.mask.data > 0.5
            spacing = stack.image.spacing[:2].double()
            through = mask.flatten(0, 1).any(0)  # (K,) slices through the brain
            brain_slices = torch.nonzero(through)[:, 0]
            if brain_slices.numel() == 0:
                continue
            if stage == "localiser":
                others = torch.nonzero(~through)[:, 0]
                keep = torch.from_numpy(rng.permutation(len(others))[: len(brain_slices)])
                others = others[keep]
                chosen = torch.cat([brain_slices, others])
                reach = data.centre_shift_mm
                draws = (len(chosen), 2) if data.shift_per_slice else 2
                shift = torch.from_numpy(rng.uniform(-reach, reach, draws)) / spacing
                centre = (torch.tensor(image.shape[:2], dtype=torch.float64) - 1) / 2 + shift
            else:  # the brain's slices and one beyond each end (inference segments a margin of
                # BrainMaskConfig.slice_margin beyond the localised ones, or every slice)
                if data.segment_all_slices:
                    chosen = torch.arange(image.shape[2])
                else:
                    first = max(int(brain_slices.min()) - 1, 0)
                    last = min(int(brain_slices.max()) + 1, image.shape[2] - 1)
                    chosen = torch.arange(first, last + 1)
                where = torch.nonzero(mask).double()
                error = torch.from_numpy(rng.normal(0.0, 5.0, 2)) / spacing
                centre = where[:, :2].mean(0) + error
            context = mask_config.segmenter_context if stage == "segmenter" else 0
            slices = neighbour_slices(image.permute(2, 0, 1)[:, None], context)[chosen]
            labels = mask.permute(2, 0, 1)[chosen, None].float()
            inputs.append(slices_to_canvas(slices, spacing, centre, size, pixel).half())
            targets.append(slices_to_canvas(labels, spacing, centre, size, pixel) > 0.5)
    return TrainingExamples(torch.cat(inputs), torch.cat(targets))


def intensity_curve(x: Tensor, knots: Tensor) -> Tensor:
    """A piecewise-linear intensity map per canvas.

    Args:
        x: (B, 1, H, W) intensities (about 0 to 1.5 after :func:`normalise_stack`).
        knots: (B, N) values of the map at N intensities evenly spaced from 0 to 2 (linear
            extrapolation beyond 2, constant below 0).

    Returns:
        (B, 1, H, W) mapped intensities.
    """
    b, n = knots.shape
    position = (x.clamp(min=0) * (n - 1) / 2).reshape(b, -1)
    index = position.floor().clamp(max=n - 2).long()
    fraction = position - index
    low = knots.gather(1, index)
    high = knots.gather(1, index + 1)
    return (low + fraction * (high - low)).reshape(x.shape)


def _augment(x: Tensor, generator: torch.Generator, curves: float = 0.0) -> Tensor:
    """Random gamma, contrast and noise per canvas (flips are applied with the targets).

    With ``curves`` > 0, that fraction of the canvases also gets a random increasing
    piecewise-linear intensity map (:func:`intensity_curve`, 8 knots) before the rest.
    """
    b = x.shape[0]
    if curves > 0:
        steps = torch.rand(b, 7, generator=generator) + 0.1
        knots = torch.cat([torch.zeros(b, 1), steps.cumsum(1)], 1)
        knots = knots / knots[:, 4:5] * (8 / 7)  # knot 4 (at 8/7) stays in place
        use = torch.rand(b, 1, 1, 1, generator=generator) < curves
        x = torch.where(use, intensity_curve(x, knots), x)
    gamma = torch.exp(torch.empty(b, 1, 1, 1).uniform_(-0.4, 0.4, generator=generator))
    scale = torch.exp(0.2 * torch.randn(b, 1, 1, 1, generator=generator))
    noise = 0.02 * torch.rand(b, 1, 1, 1, generator=generator)
    x = x.clamp(min=0) ** gamma * scale
    return x + noise * torch.randn(x.shape, generator=generator)


def dice_bce_loss(logits: Tensor, targets: Tensor) -> Tensor:
    """Binary cross entropy plus (1 - soft Dice) per canvas, averaged; (B, 1, H, W) inputs."""
    probability = torch.sigmoid(logits)
    overlap = (probability * targets).sum((1, 2, 3))
    total = (probability + targets).sum((1, 2, 3))
    dice = (2 * overlap + 1.0) / (total + 1.0)
    return functional.binary_cross_entropy_with_logits(logits, targets) + (1 - dice).mean()


def train_network(
    examples: TrainingExamples,
    net_config: SegmentationConfig,
    config: BrainMaskTrainingConfig,
    folder: str | Path | None = None,
    progress: bool = False,
    device: str | torch.device = "cpu",
) -> BrainUNet:
    """Fit a :class:`BrainUNet` to examples, checkpointing into ``folder`` and resuming from it.

    The batches are drawn and augmented on the CPU (the same stream on any device), then moved
    to ``device``.

    Args:
        examples: The canvases and targets (:func:`make_examples`).
        net_config: The U-Net's shape.
        config: Steps, batch size, learning rate, checkpoint interval, seed.
        folder: Where ``step_NNNNNNNNN`` checkpoints go (the newest is resumed); ``None`` for
            no checkpoints.
        progress: Log the loss every checkpoint interval.
        device: Where the network trains.

    Returns:
        The trained network (eval mode).
    """
    torch.manual_seed(config.seed)
    generator = torch.Generator().manual_seed(config.seed)
    net = BrainUNet(net_config).to(device)
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    schedule = cosine_schedule(optimiser, config.steps)
    start = resume_training(folder, net, optimiser, schedule, generator, device)
    net.train()
    n = examples.inputs.shape[0]
    running, began = 0.0, time.time()
    for step in range(start, config.steps):
        index = torch.randint(n, (config.batch_size,), generator=generator)
        x = examples.inputs[index].float()
        y = examples.targets[index].float()
        flips = torch.rand(2, generator=generator)
        if flips[0] < 0.5:
            x, y = x.flip(-1), y.flip(-1)
        if flips[1] < 0.5:
            x, y = x.flip(-2), y.flip(-2)
        # (2.5D: the slice order reversed, as in a stack acquired the other way; no draw in 2D,
        # so 2D runs keep their random stream)
        if x.shape[1] > 1 and float(torch.rand(1, generator=generator)) < 0.5:
            x = x.flip(1)
        x = _augment(x, generator, config.intensity_curves)
        loss = dice_bce_loss(net(x.to(device)), y.to(device))
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        schedule.step()
        running += float(loss.detach())
        done = step + 1
        if done % config.checkpoint_every == 0 or done == config.steps:
            if progress:
                log.info(
                    "step %d/%d loss %.4f (%.1f steps/s)",
                    done,
                    config.steps,
                    running / config.checkpoint_every,
                    (done - start) / (time.time() - began),
                )
            running = 0.0
            if folder is not None:
                save_training_checkpoint(
                    folder,
                    done,
                    net,
                    optimiser,
                    schedule,
                    generator,
                    {
                        "architecture": "brain_unet",
                        "net": asdict(net_config),
                        "train": asdict(config),
                    },
                )
    return net.eval()
