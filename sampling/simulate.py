"""Motion-corrupted thick-slice stacks simulated from a brain volume, with ground truth.

Frames and transforms (all mm):
    * source frame: the input volume's world frame ("atlas" in the output files);
    * canonical frame: the source frame shifted so that the mask centroid ``c`` is the origin;
    * scanner frame: where the brain is placed, ``x_s = P (x_a - c) + s`` for a random rotation
      ``P`` and offset ``s`` (``random_placement=False``: ``P = I``, ``s = 0``).

Each stack has a nominal geometry in the scanner frame (orientation, centre, slice spacing); slice
``k`` has the nominal pose ``S_k`` (slice plane -> scanner). While it is acquired, at time ``tau``,
the fetal head has moved by ``D(tau)`` about the brain centre, so the slice records the ground
truth at the true pose ``D(tau)^-1 o S_k`` (slice plane -> the ground truth's scanner frame); into
the source frame, that is ``(x_a -> x_s)^-1 o D(tau)^-1 o S_k``. Stacks are written with their
nominal affines, as a scanner would; ``truth_slices.json`` keeps the true poses.

The output folder has the layout of the bench cases (``stacks/``, ``masks/``, ``gt_volume.nii.gz``
and ``gt_mask.nii.gz`` in the scanner frame, ``case.json``, ``truth_slices.json``).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal, get_args

import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from svr.errors import ConfigFieldError
from svr.files import atomic_directory
from svr.geometry import quat_to_matrix, se3_compose, se3_inverse, so3_exp
from svr.image import Image, save_nifti, voxel_to_world
from svr.sampling.artefacts import stack_artefacts
from svr.sampling.motion import (
    Trajectory,
    load_trajectories,
    random_walk_motion,
    trajectory_motion,
)
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume
from svr.validation import (
    check_bool,
    check_choice,
    check_fraction,
    check_int,
    check_number,
    check_range,
    check_str,
)

Orientation = Literal["orthogonal", "oblique", "random"]
Motion = Literal["trajectories", "random_walk", "none"]


@dataclass(frozen=True)
class SimulationConfig:
    """What to simulate.

    Attributes:
        num_stacks: Number of stacks, >= 1.
        orientations: ``"orthogonal"`` (axial, coronal, sagittal in the scanner, repeated),
            ``"oblique"`` (orthogonal ones tilted by up to 30°) or ``"random"`` (uniform).
        thickness_mm: Slice thickness (FWHM of the through-plane PSF).
        spacing_mm: Distance between slice centres; ``None`` = the thickness. Larger gives gaps,
            smaller overlaps.
        in_plane_mm: In-plane pixel spacing.
        margin_mm: Field of view beyond the brain's radius, in-plane and through-plane.
        interleave: Acquisition order: slices ``0, m, 2m, ..., 1, 1 + m, ...`` for ``m`` =
            interleave (1 = sequential).
        slice_time_s: Time to acquire one slice (s); stacks are acquired one after another.
        motion: ``"trajectories"`` (real fetal motion, needs ``motion_path``), ``"random_walk"``
            or ``"none"``.
        motion_path: The trajectory file (``.npz``).
        motion_scale: Magnitude factor applied to the trajectories.
        random_walk_rotation_deg: Per-axis std of the random walk's final rotation (degrees).
        random_walk_translation_mm: Per-axis std of the random walk's final translation (mm).
        noise: Rician noise sigma relative to the brain's 99th-percentile intensity.
        bias_field: Strength of a smooth multiplicative bias field per stack (0 = none; 0.2
            gives roughly +-20 %).
        signal_void_probability: Chance that a slice has a signal void (a dark blob).
        random_placement: Rotate and shift the brain randomly in the scanner.
        in_plane_psf: Also apply the in-plane Gaussian PSF.
        mask_fraction: How a slice's brain mask is cut: ``None`` for the brain on the slice's
            centre plane; a number in (0, 1) for the points where more than this fraction of
            the slice's through-plane profile (its PSF) is brain, so that a slice grazing the
            brain's top or bottom, which shows it in partial volume, has it in its mask (as
            manual masks of thick slices are drawn).
        grazing_ratio: With ``mask_fraction``, which slices take the partial-volume mask:
            ``None`` for every slice; a number in (0, 1] for only the slices whose centre-plane
            mask is smaller than this fraction of their partial-volume mask (those grazing the
            brain's top or bottom, or running along its surface); the others keep the
            centre-plane mask, so their outline is not widened by the profile's tails.
        stack_turn_deg: ``(low, high)``: the fetus turns between stacks: each stack after the
            first is acquired with the brain turned (about its centre, relative to the first
            stack) by an angle drawn uniformly in this range (degrees) about a random axis, on
            top of the motion. ``(0, 0)`` (default) for no turn.
        seed: Seed of every random choice.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range, for ``grazing_ratio`` without ``mask_fraction``, and for no
            ``motion_path`` with ``"trajectories"``.
    """

    num_stacks: int = 3
    orientations: Orientation = "orthogonal"
    thickness_mm: float = 3.0
    spacing_mm: float | None = None
    in_plane_mm: float = 1.0
    margin_mm: float = 8.0
    interleave: int = 2
    slice_time_s: float = 1.5
    motion: Motion = "random_walk"
    motion_path: str | None = None
    motion_scale: float = 1.0
    random_walk_rotation_deg: float = 5.0
    random_walk_translation_mm: float = 2.0
    noise: float = 0.02
    bias_field: float = 0.0
    signal_void_probability: float = 0.0
    random_placement: bool = True
    in_plane_psf: bool = False
    mask_fraction: float | None = None
    grazing_ratio: float | None = None
    stack_turn_deg: tuple[float, float] = (0.0, 0.0)
    seed: int = 0

    def __post_init__(self) -> None:
        owner = "SimulationConfig"
        check_int(owner, "num_stacks", self.num_stacks, minimum=1)
        check_choice(owner, "orientations", self.orientations, get_args(Orientation))
        for name in ("thickness_mm", "in_plane_mm", "slice_time_s"):
            check_number(owner, name, getattr(self, name), gt=0)
        check_number(owner, "spacing_mm", self.spacing_mm, gt=0, allow_none=True)
        check_int(owner, "interleave", self.interleave, minimum=1)
        check_choice(owner, "motion", self.motion, get_args(Motion))
        check_str(owner, "motion_path", self.motion_path, allow_none=True)
        for name in (
            "margin_mm",
            "motion_scale",
            "random_walk_rotation_deg",
            "random_walk_translation_mm",
            "noise",
            "bias_field",
        ):
            check_number(owner, name, getattr(self, name), ge=0)
        check_fraction(owner, "signal_void_probability", self.signal_void_probability)
        for name in ("random_placement", "in_plane_psf"):
            check_bool(owner, name, getattr(self, name))
        fraction, ratio = self.mask_fraction, self.grazing_ratio
        check_fraction(
            owner, "mask_fraction", fraction, include_zero=False, include_one=False, allow_none=True
        )
        check_fraction(owner, "grazing_ratio", ratio, include_zero=False, allow_none=True)
        turn = check_range(
            owner, "stack_turn_deg", self.stack_turn_deg, ge=0, le=180, allow_list=True
        )
        check_int(owner, "seed", self.seed)
        if ratio is not None and fraction is None:
            raise ConfigFieldError(owner, "grazing_ratio", "None without 'mask_fraction'", ratio)
        if self.motion == "trajectories" and self.motion_path is None:
            raise ConfigFieldError(
                owner, "motion_path", "a trajectory file with motion 'trajectories'", None
            )
        object.__setattr__(self, "stack_turn_deg", turn)

    @property
    def slice_spacing_mm(self) -> float:
        """The spacing between slice centres (the thickness unless given)."""
        return self.thickness_mm if self.spacing_mm is None else self.spacing_mm


@dataclass
class SimulatedStack:
    """One simulated stack.

    Attributes:
        image: (H, W, N) slices with the nominal scanner-frame affine.
        mask: Brain mask of the observed slices, same grid.
        true_poses: (N, 4, 4) slice -> ground-truth scanner frame.
        atlas_poses: (N, 4, 4) slice -> source frame.
        acquisition_index: (N,) order in which the slices were acquired.
    """

    image: Image
    mask: Image
    true_poses: Tensor
    atlas_poses: Tensor
    acquisition_index: Tensor


@dataclass
class SimulatedCase:
    """A simulated case: stacks and ground truth."""

    stacks: list[SimulatedStack]
    gt_volume: Image
    gt_mask: Image
    info: dict = field(default_factory=dict)


def _random_rotation(generator: torch.Generator) -> Tensor:
    """A rotation uniform on SO(3) (normalised Gaussian quaternion)."""
    return quat_to_matrix(torch.randn(4, generator=generator, dtype=torch.float64))


def _axis_rotation(axis: Tensor, angle: float) -> Tensor:
    return so3_exp(axis * angle)


def stack_orientations(config: SimulationConfig, generator: torch.Generator) -> list[Tensor]:
    """(3, 3) orientation per stack: columns are the in-plane axes u, v and the slice normal."""
    base = [
        torch.eye(3, dtype=torch.float64),
        _axis_rotation(torch.tensor([1.0, 0, 0], dtype=torch.float64), math.pi / 2),
        _axis_rotation(torch.tensor([0, 1.0, 0], dtype=torch.float64), math.pi / 2),
    ]
    out = []
    for i in range(config.num_stacks):
        if config.orientations == "random":
            out.append(_random_rotation(generator))
            continue
        q = base[i % 3]
        if config.orientations == "oblique":
            axis = torch.nn.functional.normalize(
                torch.randn(3, generator=generator, dtype=torch.float64), dim=0
            )
            angle = math.radians(30.0) * float(
                torch.rand(1, generator=generator, dtype=torch.float64)
            )
            q = _axis_rotation(axis, angle) @ q
        out.append(q)
    return out


def acquisition_order(num_slices: int, interleave: int) -> Tensor:
    """(N,) acquisition index of each slice for an interleaved order ``0, m, 2m, ..., 1, ...``."""
    order = torch.cat([torch.arange(s, num_slices, interleave) for s in range(interleave)])
    index = torch.empty(num_slices, dtype=torch.long)
    index[order] = torch.arange(num_slices)
    return index


def _motions(
    config: SimulationConfig,
    times_s: np.ndarray,
    generator: torch.Generator,
    trajectories: list | None,
) -> Tensor:
    n = len(times_s)
    if config.motion == "none":
        return torch.eye(4, dtype=torch.float64).repeat(n, 1, 1)
    if config.motion == "random_walk":
        walk = random_walk_motion(
            n, generator, config.random_walk_rotation_deg, config.random_walk_translation_mm
        )
        ranks = torch.argsort(torch.argsort(torch.from_numpy(times_s)))  # step of each slice
        return walk[ranks]
    assert trajectories is not None  # loaded for motion="trajectories"
    index = int(torch.randint(len(trajectories), (1,), generator=generator))
    trajectory = trajectories[index]
    start = float(torch.rand(1, generator=generator, dtype=torch.float64)) * trajectory.duration_s
    return trajectory_motion(trajectory, times_s, start, config.motion_scale)


@dataclass
class _Scanner:
    """What every stack of a case shares: the ground truth placed in the scanner, the grids.

    Attributes:
        gt_volume: The ground truth in the scanner frame (CPU).
        gt_mask: Its brain mask, 0 or 1 (CPU).
        gt_on_device: ``gt_volume`` where slices are sampled.
        mask_on_device: ``gt_mask`` there.
        rotation: (3, 3) the placement's rotation ``P`` (``x_s = P x_c + s``).
        brain_centre: (3,) its offset ``s``: the brain centre in the scanner frame, mm.
        device: Where slices are sampled.
        source_from_scanner: (4, 4) the scanner frame into the source ("atlas") frame.
        radius: The brain's radius about its centre, mm.
        sigma: The Rician noise level (``noise`` times the brain's 99th percentile).
        num_slices: Slices per stack.
        side: Pixels per slice side.
        slice_config: The slices' grid and PSF.
        mask_config: The slice masks' grid (centre plane).
        thick_mask_config: The same through the slice thickness.
    """

    gt_volume: Image
    gt_mask: Image
    gt_on_device: Image
    mask_on_device: Image
    rotation: Tensor
    brain_centre: Tensor
    device: torch.device | str
    source_from_scanner: Tensor
    radius: float
    sigma: float
    num_slices: int
    side: int
    slice_config: SliceConfig
    mask_config: SliceConfig
    thick_mask_config: SliceConfig


def _place_in_scanner(
    volume: CanonicalVolume,
    config: SimulationConfig,
    generator: torch.Generator,
    device: torch.device | str,
) -> _Scanner:
    """Place the brain in the scanner (random unless ``random_placement`` is off); the grids."""
    brain_idx = torch.nonzero(volume.mask).to(torch.float64)
    brain_pts = voxel_to_world(volume.image.affine, brain_idx)
    radius = float(brain_pts.norm(dim=1).max())

    # Placement: x_s = P x_c + s, with x_c canonical coordinates.
    if config.random_placement:
        placement_R = _random_rotation(generator)
        placement_t = (torch.rand(3, generator=generator, dtype=torch.float64) - 0.5) * 10.0
    else:
        placement_R, placement_t = (
            torch.eye(3, dtype=torch.float64),
            torch.zeros(3, dtype=torch.float64),
        )
    scanner_from_canonical = torch.eye(4, dtype=torch.float64)
    scanner_from_canonical[:3, :3], scanner_from_canonical[:3, 3] = placement_R, placement_t
    gt_affine = scanner_from_canonical @ volume.image.affine
    gt_volume = Image(volume.image.data.clone(), gt_affine)
    gt_mask = Image(volume.mask.float(), gt_affine)
    source_from_scanner = torch.eye(4, dtype=torch.float64)
    source_from_scanner[:3, :3] = placement_R.T
    source_from_scanner[:3, 3] = volume.centre_mm - placement_R.T @ placement_t

    half = radius + config.margin_mm
    side = max(1, math.ceil(2 * half / config.in_plane_mm))
    slice_config = SliceConfig(
        size=(side, side),
        spacing_mm=config.in_plane_mm,
        thickness_mm=config.thickness_mm,
        in_plane_psf=config.in_plane_psf,
        psf_samples=3 if config.in_plane_psf else 5,
    )
    mask_config = SliceConfig(size=(side, side), spacing_mm=config.in_plane_mm)
    return _Scanner(
        gt_volume=gt_volume,
        gt_mask=gt_mask,
        gt_on_device=gt_volume.to(device),
        mask_on_device=gt_mask.to(device),
        rotation=placement_R,
        brain_centre=placement_t,
        device=device,
        source_from_scanner=source_from_scanner,
        radius=radius,
        sigma=config.noise * float(np.percentile(volume.image.data[volume.mask].numpy(), 99)),
        num_slices=max(1, math.ceil(2 * half / config.slice_spacing_mm)),
        side=side,
        slice_config=slice_config,
        mask_config=mask_config,
        thick_mask_config=dataclasses.replace(mask_config, thickness_mm=config.thickness_mm),
    )


def _stack_motion(
    config: SimulationConfig,
    stack: int,
    times_s: np.ndarray,
    generator: torch.Generator,
    trajectories: list[Trajectory] | None,
) -> Tensor:
    """(K, 4, 4) head motion at each slice's time; after the first stack, turned as a whole."""
    motion = _motions(config, times_s, generator, trajectories)
    if stack > 0 and config.stack_turn_deg[1] > 0:
        low, high = config.stack_turn_deg
        angle = math.radians(
            low + (high - low) * float(torch.rand(1, generator=generator, dtype=torch.float64))
        )
        axis = torch.nn.functional.normalize(
            torch.randn(3, generator=generator, dtype=torch.float64), dim=0
        )
        turn = torch.eye(4, dtype=torch.float64)
        turn[:3, :3] = _axis_rotation(axis, angle)
        motion = se3_compose(motion, turn)
    return motion


def _simulate_stack(
    scanner: _Scanner,
    config: SimulationConfig,
    stack: int,
    orient: Tensor,
    generator: torch.Generator,
    trajectories: list[Trajectory] | None,
) -> SimulatedStack:
    """Stack number ``stack``, oriented by the (3, 3) ``orient``, acquired under motion."""
    num_slices, side, spacing = scanner.num_slices, scanner.side, config.slice_spacing_mm
    centre = (
        scanner.brain_centre + (torch.rand(3, generator=generator, dtype=torch.float64) - 0.5) * 6.0
    )
    offsets = (torch.arange(num_slices, dtype=torch.float64) - (num_slices - 1) / 2) * spacing
    nominal = torch.eye(4, dtype=torch.float64).repeat(num_slices, 1, 1)
    nominal[:, :3, :3] = orient
    nominal[:, :3, 3] = centre + offsets[:, None] * orient[:, 2]
    acq = acquisition_order(num_slices, config.interleave)
    times = ((stack * num_slices + acq).double() * config.slice_time_s).numpy()
    motion = _stack_motion(config, stack, times, generator, trajectories)
    # D acts about the brain centre.
    about_centre = torch.eye(4, dtype=torch.float64)
    about_centre[:3, 3] = scanner.brain_centre
    moved = se3_compose(se3_compose(about_centre, motion), se3_inverse(about_centre))
    true_poses = se3_compose(se3_inverse(moved), nominal)
    on_device = true_poses.to(scanner.device)
    slices = sample_slices(scanner.gt_on_device, on_device, scanner.slice_config).cpu()
    masks = _slice_masks(
        scanner.mask_on_device, on_device, scanner.mask_config, scanner.thick_mask_config, config
    )
    slices = stack_artefacts(
        slices,
        nominal,
        config.in_plane_mm,
        scanner.brain_centre,
        scanner.radius,
        config.bias_field,
        config.signal_void_probability,
        scanner.sigma if config.noise > 0 else None,
        generator,
    )
    affine = torch.eye(4, dtype=torch.float64)
    affine[:3, :3] = orient * torch.tensor(
        [config.in_plane_mm, config.in_plane_mm, spacing], dtype=torch.float64
    )
    affine[:3, 3] = nominal[0, :3, 3] - (side - 1) / 2 * config.in_plane_mm * (
        orient[:, 0] + orient[:, 1]
    )
    return SimulatedStack(
        image=Image(slices.permute(1, 2, 0).contiguous(), affine),
        mask=Image(masks.permute(1, 2, 0).contiguous(), affine),
        true_poses=true_poses,
        atlas_poses=se3_compose(scanner.source_from_scanner, true_poses),
        acquisition_index=acq,
    )


def simulate_case(
    volume: CanonicalVolume,
    config: SimulationConfig,
    progress: bool = False,
    device: torch.device | str = "cpu",
    trajectories: list[Trajectory] | None = None,
) -> SimulatedCase:
    """Simulate motion-corrupted stacks from a canonical volume.

    Args:
        volume: The brain (its source frame is the "atlas" frame of the outputs).
        config: What to simulate.
        progress: Show a progress bar over stacks.
        device: Where slices are sampled; random draws and results stay on the CPU, so the
            output does not depend on the device beyond floating-point rounding.
        trajectories: The recordings of ``config.motion_path`` already loaded (to simulate many
            cases without reading the file each time); ``None`` reads them when needed.

    Returns:
        The simulated case (CPU tensors).
    """
    generator = torch.Generator().manual_seed(config.seed)
    if config.motion != "trajectories":
        trajectories = None
    elif trajectories is None:
        assert config.motion_path is not None  # checked by SimulationConfig
        trajectories = load_trajectories(config.motion_path)
    scanner = _place_in_scanner(volume, config, generator, device)
    orientations = stack_orientations(config, generator)
    stacks = [
        _simulate_stack(scanner, config, s, orient, generator, trajectories)
        for s, orient in enumerate(tqdm(orientations, desc="stacks", disable=not progress))
    ]
    info = {
        "thickness": [config.thickness_mm] * config.num_stacks,
        "spacing": config.slice_spacing_mm,
        "inplane": config.in_plane_mm,
        "atlas_centre_mm": volume.centre_mm.tolist(),
        "scanner_from_atlas_R": scanner.rotation.tolist(),
        "scanner_centre": scanner.brain_centre.tolist(),
        "simulation": asdict(config),
    }
    return SimulatedCase(stacks, scanner.gt_volume, scanner.gt_mask, info)


def _slice_masks(
    mask: Image,
    poses: Tensor,
    centre_plane: SliceConfig,
    thick: SliceConfig,
    config: SimulationConfig,
) -> Tensor:
    """The slices' brain masks as ``SimulationConfig.mask_fraction`` and ``grazing_ratio`` say.

    Args:
        mask: The brain mask (0 or 1) in the scanner frame.
        poses: (K, 4, 4) slice-to-scanner poses (mm).
        centre_plane: The slices without thickness (the centre-plane masks).
        thick: The slices with the stack's thickness (the partial-volume masks).
        config: The acquisition.

    Returns:
        (K, H, W) float masks (0 or 1) on the CPU.
    """
    if config.mask_fraction is None:
        return (sample_slices(mask, poses, centre_plane) > 0.5).float().cpu()
    partial = sample_slices(mask, poses, thick) > config.mask_fraction
    if config.grazing_ratio is not None:
        centre = sample_slices(mask, poses, centre_plane) > 0.5
        area = centre.flatten(1).sum(1), partial.flatten(1).sum(1)
        grazing = area[0] < config.grazing_ratio * area[1]  # (K,)
        partial = torch.where(grazing[:, None, None], partial, centre)
    return partial.float().cpu()


def _pose_json(T: Tensor) -> dict:
    return {"R": T[:3, :3].tolist(), "t": T[:3, 3].tolist()}


def pose_from_json(entry: dict) -> Tensor:
    """(4, 4) float64 a pose as ``truth_slices.json`` stores it (``{"R": 3x3, "t": 3}``, mm)."""
    matrix = torch.eye(4, dtype=torch.float64)
    matrix[:3, :3] = torch.tensor(entry["R"], dtype=torch.float64)
    matrix[:3, 3] = torch.tensor(entry["t"], dtype=torch.float64)
    return matrix


def write_case(
    case: SimulatedCase, out_dir: str | os.PathLike[str], overwrite: bool = False, source: str = ""
) -> Path:
    """Write a simulated case in the bench-case layout, atomically (a folder renamed into place).

    Args:
        case: The case.
        out_dir: The folder to create.
        overwrite: Replace an existing folder.
        source: Name of the source volume, recorded in ``case.json``.

    Returns:
        The folder.

    Raises:
        OutputExistsError: If the folder exists and ``overwrite`` is false.
    """
    with atomic_directory(out_dir, overwrite) as tmp:
        (tmp / "stacks").mkdir()
        (tmp / "masks").mkdir()
        truth: dict[str, list] = {"stacks": []}
        for i, stack in enumerate(case.stacks):
            save_nifti(stack.image, tmp / "stacks" / f"stack{i}.nii.gz")
            save_nifti(stack.mask, tmp / "masks" / f"stack{i}_mask.nii.gz")
            slices = [
                {
                    "scanner": _pose_json(stack.true_poses[k]),
                    "atlas": _pose_json(stack.atlas_poses[k]),
                    "acq_index": int(stack.acquisition_index[k]),
                }
                for k in range(stack.true_poses.shape[0])
            ]
            truth["stacks"].append({"file": f"stacks/stack{i}.nii.gz", "slices": slices})
        save_nifti(case.gt_volume, tmp / "gt_volume.nii.gz")
        save_nifti(case.gt_mask, tmp / "gt_mask.nii.gz")
        (tmp / "case.json").write_text(json.dumps({**case.info, "source": source}, indent=1) + "\n")
        (tmp / "truth_slices.json").write_text(json.dumps(truth) + "\n")
    return Path(out_dir)
