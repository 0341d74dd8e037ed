"""Training the slice refiner on packets of slices cut from atlas brains with simulated motion.

Every training example is an interleaved packet as a reconstruction sees it after its stacks and
packets were placed (:mod:`svr.reconstruction.initialisation`): ``L`` parallel thick slices of a
stack at a random orientation, acquired one after another while the head moved (a random walk of
rigid motions about the brain's centre, its step size drawn per packet, up to a few degrees per
slice), and *placed* by one rigid estimate of the packet, the robust mean of its true poses turned
by a random error (up to ``max_turn_deg``). Each slice's residual ``D_i = T_current_i^-1 o T_i``
(slice frame) is the label. The reference beside each slice is the same brain blurred by a random
Gaussian (a reconstruction from roughly placed slices is blurred) and the slice and the reference
share a random intensity curve, so contrast is a nuisance, not a cue; the slice gets its thick
PSF, noise and its brain mask. ``context="none"`` networks see the packet's slices one by one,
``"sequence"`` ones the packet at once; both draw the same examples at one budget.

The batches are addressed by the step (each step's generator is seeded from the run's seed and
the step), so a run resumed from a checkpoint (:mod:`svr.models.resume`) continues exactly.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import NamedTuple

import torch
from scipy.ndimage import gaussian_filter
from torch import Tensor

from svr.geometry import se3_compose, se3_inverse, se3_to_vector, so3_exp, vector_to_se3
from svr.image import Image
from svr.losses.metric_weights import default_metric_weights, estimate_metric_weights
from svr.models.network import loss_function
from svr.models.resume import cosine_schedule, resume_training, save_training_checkpoint
from svr.models.slice_refiner import SLICE_REFINER, SliceRefinerConfig, SliceRefinerNet
from svr.sampling.poses import pose_labels
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume, downsample_volume
from svr.validation import check_choice, check_int, check_number, check_range

__all__ = [
    "PacketScene",
    "RefinerBrain",
    "RefinerTrainingConfig",
    "draw_packets",
    "metric_weights",
    "prepare_brains",
    "render_inputs",
    "residual_errors",
    "train_slice_refiner",
]

log = logging.getLogger(__name__)

BLUR_MM = (0.0, 1.0, 2.0, 3.0)
"""The reference's Gaussian blurs (standard deviation, mm), one drawn per packet."""


@dataclass(frozen=True)
class RefinerTrainingConfig:
    """How the slice refiner is trained.

    Attributes:
        steps: Optimiser steps, >= 1.
        packets_per_step: Packets per batch, >= 1.
        packet_length: Slices per packet, >= 2.
        learning_rate: Adam's initial rate (cosine decay to 5 % of it).
        max_turn_deg: Largest error of a packet's placement (degrees).
        placement_shift_mm: Per-axis standard deviation of its shift (mm).
        max_step_deg: Largest per-slice step of the head's random walk (degrees; drawn per packet).
        thickness_mm: (low, high) slice thickness (mm).
        noise: (low, high) Rician noise, a fraction of the slice's bright end.
        gamma: (low, high) exponent of the shared intensity curve.
        metric: The SE(3) loss's inner product Z: ``"data"``, estimated from the residuals the
            training draws (:func:`svr.losses.estimate_metric_weights`: each component by the
            inverse of its variance, so that rotations of a few degrees weigh as much as shifts of
            a few millimetres), or ``"default"``, ``diag(1, 1, 1, 1/L^2, ...)`` with ``L =
            metric_length_mm``.
        metric_length_mm: ``L`` of the ``"default"`` metric.
        checkpoint_every: Steps between checkpoints.
        seed: Seed of every draw.
        pure_rotation: A diagnostic: every slice's current pose is its true pose turned about the
            slice's centre by a random rotation up to ``max_turn_deg`` (no shift), so that the
            residual is a rotation alone.
        pure_rotation_shift_mm: With ``pure_rotation``, also shift each slice by a random
            offset (per-axis standard deviation, mm, in the slice's frame).
        other_reference: Probability that a packet's reference is another brain (one of the
            slices' brain's ``partners``, e.g. a neighbouring age), as in a reconstruction whose
            reference is an atlas rather than the fetus: the label stays the slices' true pose in
            the shared canonical frame, so the network learns to match anatomy that differs.

    Raises:
        ConfigFieldError: On construction, naming the field.
    """

    steps: int = 6000
    packets_per_step: int = 4
    packet_length: int = 8
    learning_rate: float = 1e-3
    max_turn_deg: float = 30.0
    placement_shift_mm: float = 3.0
    max_step_deg: float = 6.0
    thickness_mm: tuple[float, float] = (2.5, 4.0)
    noise: tuple[float, float] = (0.01, 0.05)
    gamma: tuple[float, float] = (0.6, 1.6)
    metric: str = "data"
    metric_length_mm: float = 20.0
    checkpoint_every: int = 250
    seed: int = 0
    pure_rotation: bool = False
    pure_rotation_shift_mm: float = 0.0
    other_reference: float = 0.0

    def __post_init__(self) -> None:
        owner = "RefinerTrainingConfig"
        for name, minimum in (("steps", 1), ("packets_per_step", 1), ("packet_length", 2)):
            check_int(owner, name, getattr(self, name), minimum=minimum)
        check_int(owner, "checkpoint_every", self.checkpoint_every, minimum=1)
        check_int(owner, "seed", self.seed, minimum=0)
        for name in ("learning_rate", "metric_length_mm"):
            check_number(owner, name, getattr(self, name), gt=0)
        for name in ("max_turn_deg", "placement_shift_mm", "max_step_deg"):
            check_number(owner, name, getattr(self, name), ge=0)
        for name in ("thickness_mm", "noise", "gamma"):
            check_range(owner, name, getattr(self, name), ge=0)
        check_choice(owner, "metric", self.metric, ("data", "default"))
        check_number(owner, "other_reference", self.other_reference, ge=0, le=1)


class RefinerBrain(NamedTuple):
    """A training brain at the refiner's scale.

    Attributes:
        sharp: The brain-masked, normalised volume (canonical mm) the slices are cut from.
        blurred: The same at each blur of :data:`BLUR_MM`, the references.
        mask: Its brain mask (float 0/1), for the slices' masks.
        radius_mm: Half the brain's largest extent (mm), for where packets are placed.
    """

    sharp: Image
    blurred: tuple[Image, ...]
    mask: Image
    radius_mm: float


def prepare_brains(volumes: Sequence[CanonicalVolume], factor: int = 2) -> list[RefinerBrain]:
    """The training brains, downsampled by ``factor`` and blurred once for every reference blur.

    Args:
        volumes: Canonical volumes (e.g. atlas ages of several families).
        factor: Downsampling factor (2: 0.8 mm atlases to 1.6 mm).

    Returns:
        One :class:`RefinerBrain` per volume.
    """
    brains = []
    for volume in volumes:
        small = downsample_volume(volume, factor) if factor > 1 else volume
        image = small.image.to("cpu", torch.float32)
        spacing = image.spacing.double().numpy()
        data = image.data.numpy()
        blurred = tuple(
            image
            if sigma == 0
            else Image(
                torch.from_numpy(gaussian_filter(data, sigma / spacing)).float(), image.affine
            )
            for sigma in BLUR_MM
        )
        idx = torch.nonzero(small.mask).double()
        points = idx @ image.affine[:3, :3].T.double() + image.affine[:3, 3].double()
        radius = float(points.norm(dim=1).max())
        brains.append(RefinerBrain(image, blurred, Image(small.mask.float(), image.affine), radius))
    return brains


def _random_rotations(n: int, max_deg: Tensor | float, generator: torch.Generator) -> Tensor:
    """(n, 3, 3) float64 rotations about random axes by angles uniform in [0, max_deg]."""
    axis = torch.randn(n, 3, generator=generator, dtype=torch.float64)
    axis = axis / axis.norm(dim=1, keepdim=True)
    angle = torch.rand(n, generator=generator, dtype=torch.float64) * torch.as_tensor(max_deg)
    return so3_exp(axis * torch.deg2rad(angle)[:, None])


class PacketBatch(NamedTuple):
    """A batch of packets (:func:`draw_packets`).

    Attributes:
        inputs: (B, L, C, H, W) float32 slices and reference planes.
        labels: (B, L, D) the residuals' labels in the representation.
        residuals: (B, L, 6) float64 the residuals' pose vectors (rad, mm).
        times: (B, L) float32 each slice's time in its packet.
        poses: (B, L, 6) float32 each slice's current pose relative to its packet's (rad, mm).
        valid: (B, L) bool, slices with enough brain to be learned from.
    """

    inputs: Tensor
    labels: Tensor
    residuals: Tensor
    times: Tensor
    poses: Tensor
    valid: Tensor


def _packet_poses(
    brain: RefinerBrain, config: RefinerTrainingConfig, thickness: float, generator: torch.Generator
) -> tuple[Tensor, Tensor]:
    """(L, 4, 4) true and current poses of one packet's slices (canonical mm)."""
    length = config.packet_length
    orientation = _random_rotations(1, 180.0, generator)[0]
    gap = 2.0 * thickness  # two interleaved packets: every other plane of the stack
    z = (torch.arange(length, dtype=torch.float64) - (length - 1) / 2) * gap
    z = z + (torch.rand(1, generator=generator, dtype=torch.float64) - 0.5) * gap
    nominal = torch.eye(4, dtype=torch.float64).repeat(length, 1, 1)
    nominal[:, :3, :3] = orientation
    nominal[:, :3, 3] = orientation[:, 2][None] * z[:, None]
    nominal[:, :3, 3] += torch.randn(3, generator=generator, dtype=torch.float64) * 3.0
    step = torch.rand(1, generator=generator, dtype=torch.float64) * config.max_step_deg
    steps = _random_rotations(length, step, generator)
    motion = torch.eye(4, dtype=torch.float64).repeat(length, 1, 1)
    shift = torch.randn(length, 3, generator=generator, dtype=torch.float64) * (step / 4)
    for i in range(1, length):
        motion[i, :3, :3] = steps[i] @ motion[i - 1, :3, :3]
        motion[i, :3, 3] = motion[i - 1, :3, 3] + shift[i]
    true = se3_compose(motion, nominal)
    placement = torch.eye(4, dtype=torch.float64)
    placement[:3, :3] = _random_rotations(1, config.max_turn_deg, generator)[0]
    placement[:3, 3] = torch.randn(3, generator=generator, dtype=torch.float64)
    placement[:3, 3] *= config.placement_shift_mm
    current = se3_compose(se3_compose(placement, _chordal_mean(motion))[None], nominal)
    if config.pure_rotation:
        turn = torch.eye(4, dtype=torch.float64).repeat(length, 1, 1)
        turn[:, :3, :3] = _random_rotations(length, config.max_turn_deg, generator)
        if config.pure_rotation_shift_mm > 0:
            shift = torch.randn(length, 3, generator=generator, dtype=torch.float64)
            turn[:, :3, 3] = shift * config.pure_rotation_shift_mm
        current = se3_compose(true, se3_inverse(turn))
    return true, current


def _chordal_mean(poses: Tensor) -> Tensor:
    """(4, 4) the chordal mean of rigid poses: the nearest rotation to the mean matrix, mean shift.

    Cheap, and close to the robust mean for the small spreads of one packet.
    """
    u, _, vh = torch.linalg.svd(poses[:, :3, :3].mean(0))
    rotation = u @ vh
    if float(torch.det(rotation)) < 0:
        u = u.clone()
        u[:, -1] = -u[:, -1]
        rotation = u @ vh
    mean = torch.eye(4, dtype=poses.dtype)
    mean[:3, :3] = rotation
    mean[:3, 3] = poses[:, :3, 3].mean(0)
    return mean


def _planes(poses: Tensor, offsets: Sequence[float]) -> Tensor:
    """(L * P, 4, 4) the poses moved by each offset along their normals (slice-major)."""
    shifts = torch.eye(4, dtype=torch.float64).repeat(len(offsets), 1, 1)
    shifts[:, 2, 3] = torch.tensor(offsets, dtype=torch.float64)
    return se3_compose(poses[:, None], shifts[None]).reshape(-1, 4, 4)


class PacketScene(NamedTuple):
    """What one drawn packet needs to be seen again from other current poses (an iterated step).

    Attributes:
        slices: (L, H, W) the acquired slices (PSF, noise, brain mask), before the intensity curve.
        reference: The blurred reference volume the planes are resampled from.
        gamma: The exponent of the shared intensity curve.
        true: (L, 4, 4) float64 the slices' true poses (canonical mm).
        current: (L, 4, 4) float64 their current poses.
        valid: (L,) bool, slices with enough brain to be learned from.
    """

    slices: Tensor
    reference: Image
    gamma: float
    true: Tensor
    current: Tensor
    valid: Tensor


def render_inputs(scene: PacketScene, current: Tensor, model: SliceRefinerConfig) -> Tensor:
    """(L, C, H, W) float32 the network's inputs for the scene's slices at ``current`` poses.

    Args:
        scene: The packet (:func:`draw_packets` with ``scenes``).
        current: (L, 4, 4) float64 the slices' current poses (canonical mm).
        model: The inputs the network takes.
    """
    size = model.size
    thin = SliceConfig(size=size, spacing_mm=model.spacing_mm)
    planes = sample_slices(scene.reference, _planes(current, model.plane_offsets_mm), thin)
    planes = planes.reshape(len(current), len(model.plane_offsets_mm), *size)
    inputs = torch.cat([scene.slices[:, None], planes], dim=1).clamp_min(0).pow(scene.gamma)
    return inputs.float()


def draw_packets(
    brains: Sequence[RefinerBrain],
    model: SliceRefinerConfig,
    config: RefinerTrainingConfig,
    generator: torch.Generator,
    scenes: list[PacketScene] | None = None,
    partners: Sequence[Sequence[int]] | None = None,
) -> PacketBatch:
    """``config.packets_per_step`` packets of ``config.packet_length`` slices (module docstring).

    Args:
        brains: The training brains (:func:`prepare_brains`).
        model: The inputs the network takes (size, spacing, reference planes, representation).
        config: The draws' ranges.
        generator: The batch's random generator.
        scenes: If given, each packet's :class:`PacketScene` is appended to it.
        partners: For each brain, the indices of the brains its references may come from with
            ``config.other_reference`` (``None``: always its own).

    Returns:
        The batch.
    """
    parts: list[tuple[Tensor, ...]] = []
    size, spacing = model.size, model.spacing_mm
    for _ in range(config.packets_per_step):
        index = int(torch.randint(len(brains), (1,), generator=generator))
        brain = brains[index]
        low, high = config.thickness_mm
        thickness = low + (high - low) * float(torch.rand(1, generator=generator))
        true, current = _packet_poses(brain, config, thickness, generator)
        thick = SliceConfig(size=size, spacing_mm=spacing, thickness_mm=thickness, psf_samples=3)
        thin = SliceConfig(size=size, spacing_mm=spacing)
        slices = sample_slices(brain.sharp, true, thick)
        mask = sample_slices(brain.mask, true, thin) > 0.5
        blur = int(torch.randint(len(BLUR_MM), (1,), generator=generator))
        reference = brain.blurred[blur]
        if partners and partners[index] and config.other_reference > 0:
            other = float(torch.rand(1, generator=generator)) < config.other_reference
            pick = int(torch.randint(len(partners[index]), (1,), generator=generator))
            if other:
                reference = brains[partners[index][pick]].blurred[blur]
        noise = config.noise[0] + (config.noise[1] - config.noise[0]) * torch.rand(
            1, generator=generator
        )
        real = slices + noise * torch.randn(slices.shape, generator=generator)
        imaginary = noise * torch.randn(slices.shape, generator=generator)
        slices = torch.sqrt(real.square() + imaginary.square()) * mask
        gamma = config.gamma[0] + (config.gamma[1] - config.gamma[0]) * float(
            torch.rand(1, generator=generator)
        )
        valid = mask.flatten(1).float().mean(1) > 0.05
        scene = PacketScene(slices, reference, gamma, true, current, valid)
        if scenes is not None:
            scenes.append(scene)
        inputs = render_inputs(scene, current, model)
        residual = se3_to_vector(se3_compose(se3_inverse(current), true))
        mean = _chordal_mean(current)
        relative = se3_to_vector(se3_compose(se3_inverse(mean)[None], current)).float()
        times = torch.arange(len(true), dtype=torch.float32)
        parts.append((inputs, residual, times, relative, valid))
    inputs, residuals, times, poses, valid = (torch.stack(p) for p in zip(*parts, strict=True))
    labels = pose_labels(residuals, model.representation).float()
    return PacketBatch(inputs, labels, residuals, times, poses, valid)


def _outputs(net: SliceRefinerNet, batch: PacketBatch) -> Tensor:
    """(B, L, D) the network's outputs: packet by packet, or slice by slice."""
    if net.config.context == "sequence":
        return net(batch.inputs, batch.times, batch.poses, ~batch.valid)
    b, length = batch.inputs.shape[:2]
    return net(batch.inputs.flatten(0, 1)).reshape(b, length, -1)


def metric_weights(
    brains: Sequence[RefinerBrain], model: SliceRefinerConfig, config: RefinerTrainingConfig
) -> Tensor:
    """(6,) the SE(3) loss's diagonal Z for ``config.metric`` (from 16 batches of residuals)."""
    if config.metric == "default":
        return default_metric_weights(config.metric_length_mm)
    residuals = []
    for index in range(16):
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + 10**9 + index)
        batch = draw_packets(brains, model, config, generator)
        residuals.append(batch.residuals[batch.valid])
    return estimate_metric_weights(torch.cat(residuals)).float()


COORDS_WEIGHT = 0.1
"""Weight of the ``"coords"`` head's point loss beside the pose loss."""


def _coords_loss(net: SliceRefinerNet, batch: PacketBatch) -> Tensor:
    """Mean distance (in units of 10 mm) of the predicted cell points from where they truly are."""
    inputs = batch.inputs[batch.valid]
    points = net.points(inputs)[..., :3]
    truth = vector_to_se3(batch.residuals[batch.valid].double()).to(points)
    cells = net.cells.to(points)
    true_points = cells @ truth[:, :3, :3].transpose(1, 2) + truth[:, None, :3, 3]
    return (points - true_points).norm(dim=-1).mean() / 10.0


def _checkpoint_config(model: SliceRefinerConfig, config: RefinerTrainingConfig) -> dict:
    return {
        "architecture": SLICE_REFINER,
        "model": model.to_dict(),
        "training": asdict(config),
    }


def train_slice_refiner(
    volumes: Sequence[CanonicalVolume],
    model: SliceRefinerConfig,
    config: RefinerTrainingConfig,
    folder: str | Path | None = None,
    device: str | torch.device = "cpu",
    minutes: float | None = None,
    progress: Callable[[int, float], None] | None = None,
    partners: Sequence[Sequence[int]] | None = None,
    init: SliceRefinerNet | None = None,
) -> SliceRefinerNet:
    """Train (or resume training) a slice refiner.

    Args:
        volumes: The training brains in canonical space.
        model: The network.
        config: The training.
        folder: Where ``step_NNNNNNNNN`` checkpoints go (the newest is resumed); ``None`` for
            none.
        device: Where the network trains.
        minutes: Stop (after a checkpoint) once this much wall time has passed, or ``None``.
        progress: Called with ``(step, loss)`` after every step.
        partners: For each volume, the volumes its references may come from
            (``config.other_reference``; :func:`draw_packets`).
        init: A trained refiner of the same ``model`` whose weights the first step starts from
            (a warm start; a resumed run's checkpoint takes precedence), or ``None``.

    Returns:
        The trained network, in eval mode.
    """
    brains = prepare_brains(volumes)
    net = SliceRefinerNet(model).to(device)
    if init is not None:
        net.load_state_dict(init.state_dict())  # a float16 export's values, as float32
    optimiser = torch.optim.Adam(net.parameters(), lr=config.learning_rate)
    schedule = cosine_schedule(optimiser, config.steps)
    start = resume_training(folder, net, optimiser, schedule, None, device)
    weights = metric_weights(brains, model, config)
    log.info("metric weights Z = %s", [round(float(w), 4) for w in weights])
    se3 = model.representation == "se3"
    loss_of = loss_function(model.representation, weights if se3 else None)
    began = time.perf_counter()
    checkpoint = {**_checkpoint_config(model, config), "metric_weights": weights.tolist()}
    net.train()
    for step in range(start, config.steps):
        generator = torch.Generator().manual_seed(config.seed * 1_000_003 + step)
        batch = draw_packets(brains, model, config, generator, partners=partners)
        on_device = PacketBatch(*(part.to(device) for part in batch))
        outputs = _outputs(net, on_device)
        valid = on_device.valid
        loss = loss_of(outputs[valid], on_device.labels[valid])
        if model.head == "coords":
            loss = loss + COORDS_WEIGHT * _coords_loss(net, on_device)
        optimiser.zero_grad(set_to_none=True)
        loss.backward()
        optimiser.step()
        schedule.step()
        if progress is not None:
            progress(step + 1, float(loss.detach()))
        done = step + 1
        late = minutes is not None and time.perf_counter() - began > 60.0 * minutes
        if folder is not None and (
            done % config.checkpoint_every == 0 or done == config.steps or late
        ):
            save_training_checkpoint(folder, done, net, optimiser, schedule, None, checkpoint)
        if late:
            log.info("stopped after %d steps (--minutes %g)", done, minutes)
            break
    return net.eval()


def residual_errors(net: SliceRefinerNet, batch: PacketBatch) -> tuple[Tensor, Tensor]:
    """(V,) rotation (degrees) and translation (mm) errors after one step, on the valid slices.

    For validation: compare with the residuals' own size (the errors of the current poses).
    """
    with torch.no_grad():
        predicted = net.to_pose(_outputs(net, batch))
    error = se3_to_vector(
        se3_compose(
            se3_inverse(_as_matrix(predicted[batch.valid])),
            _as_matrix(batch.residuals[batch.valid].to(predicted)),
        )
    )
    return torch.rad2deg(error[:, :3].norm(dim=1)), error[:, 3:].norm(dim=1)


def _as_matrix(vectors: Tensor) -> Tensor:
    return vector_to_se3(vectors.double())
