"""``svr simulate``: motion-corrupted stacks with ground truth, in the bench-case layout."""

from __future__ import annotations

import argparse

from svr.cli.common import (
    HelpFormatter,
    add_common_options,
    add_volume_options,
    load_input_volume,
    option_errors,
    positive_float,
    positive_int,
    resolve_device,
)
from svr.cli.defaults import SIMULATION
from svr.files import check_output_path

DESCRIPTION = """\
Simulate motion-corrupted thick-slice stacks from a brain volume (or the built-in phantom):
per-slice rigid motion (real fetal trajectories or a random walk), slice PSF, interleaved
acquisition, Rician noise, bias field and signal voids, with the brain placed at random in the
scanner. Writes stacks/, masks/, gt_volume.nii.gz, gt_mask.nii.gz (scanner frame), case.json and
truth_slices.json (every slice's true pose), the layout of the bench cases.

examples:
  svr simulate --output-dir case1
  svr simulate --input-volume srr.nii.gz --input-mask mask.nii.gz --output-dir case2 \\
      --num-stacks 4 --orientations oblique --motion trajectories \\
      --motion-path svort_fetal_motion_trajectories.npz --motion-scale 0.3
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr simulate``."""
    p = subparsers.add_parser(
        "simulate",
        help="simulate motion-corrupted stacks with ground truth",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument("--output-dir", required=True, help="folder to create")
    add_volume_options(p)
    _add_acquisition_options(p)
    _add_motion_options(p)
    _add_artefact_options(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output-dir")
    add_common_options(p)


def _add_acquisition_options(p: argparse.ArgumentParser) -> None:
    """The stacks' geometry and acquisition timing."""
    p.add_argument(
        "--num-stacks", type=positive_int, default=SIMULATION["num_stacks"], help="number of stacks"
    )
    p.add_argument(
        "--orientations",
        choices=["orthogonal", "oblique", "random"],
        default=SIMULATION["orientations"],
        help="stack orientations in the scanner",
    )
    p.add_argument(
        "--thickness",
        type=positive_float,
        default=SIMULATION["thickness_mm"],
        help="slice thickness in mm (FWHM of the through-plane PSF)",
    )
    p.add_argument(
        "--slice-spacing",
        type=positive_float,
        default=None,
        help="distance between slice centres in mm (default: the thickness)",
    )
    p.add_argument(
        "--in-plane-resolution",
        type=positive_float,
        default=SIMULATION["in_plane_mm"],
        help="in-plane pixel spacing in mm",
    )
    p.add_argument("--in-plane-psf", action="store_true", help="also apply the in-plane PSF")
    p.add_argument(
        "--interleave",
        type=positive_int,
        default=SIMULATION["interleave"],
        help="acquisition interleave factor (1 = sequential)",
    )
    p.add_argument(
        "--slice-time",
        type=positive_float,
        default=SIMULATION["slice_time_s"],
        help="seconds per slice",
    )


def _add_motion_options(p: argparse.ArgumentParser) -> None:
    """The fetal motion during and between stacks."""
    p.add_argument(
        "--motion",
        choices=["random-walk", "trajectories", "none"],
        default="random-walk",
        help="fetal motion model",
    )
    p.add_argument(
        "--motion-path", help="fetal motion trajectories (.npz) for --motion trajectories"
    )
    p.add_argument(
        "--motion-scale",
        type=float,
        default=SIMULATION["motion_scale"],
        help="magnitude factor for the trajectories",
    )
    p.add_argument(
        "--stack-turn-deg",
        type=float,
        nargs=2,
        metavar=("LOW", "HIGH"),
        default=list(SIMULATION["stack_turn_deg"]),
        help="the fetus turns between stacks: each stack after the first sees the brain turned "
        "by an angle drawn in [LOW, HIGH] degrees about a random axis (0 0: no turn)",
    )
    p.add_argument(
        "--rotation-deg",
        type=float,
        default=SIMULATION["random_walk_rotation_deg"],
        help="random walk: per-axis std of the final rotation (degrees)",
    )
    p.add_argument(
        "--translation-mm",
        type=float,
        default=SIMULATION["random_walk_translation_mm"],
        help="random walk: per-axis std of the final translation (mm)",
    )


def _add_artefact_options(p: argparse.ArgumentParser) -> None:
    """Noise, bias field, signal voids and the brain's placement."""
    p.add_argument(
        "--noise",
        type=float,
        default=SIMULATION["noise"],
        help="Rician noise sigma relative to the brain's 99th-percentile intensity",
    )
    p.add_argument(
        "--bias-field",
        type=float,
        default=SIMULATION["bias_field"],
        help="bias field strength (0 = none, 0.2 ~ +-20%%)",
    )
    p.add_argument(
        "--signal-voids",
        type=float,
        default=SIMULATION["signal_void_probability"],
        help="probability of a signal void per slice",
    )
    p.add_argument(
        "--no-random-placement",
        action="store_true",
        help="keep the brain's orientation and position in the scanner",
    )


_OPTIONS = {
    "num_stacks": "--num-stacks",
    "orientations": "--orientations",
    "thickness_mm": "--thickness",
    "spacing_mm": "--slice-spacing",
    "in_plane_mm": "--in-plane-resolution",
    "in_plane_psf": "--in-plane-psf",
    "interleave": "--interleave",
    "slice_time_s": "--slice-time",
    "motion": "--motion",
    "motion_path": "--motion-path",
    "motion_scale": "--motion-scale",
    "random_walk_rotation_deg": "--rotation-deg",
    "random_walk_translation_mm": "--translation-mm",
    "noise": "--noise",
    "bias_field": "--bias-field",
    "signal_void_probability": "--signal-voids",
    "random_placement": "--no-random-placement",
    "stack_turn_deg": "--stack-turn-deg",
    "seed": "--seed",
}
"""The option behind each SimulationConfig field (:func:`~svr.cli.common.option_errors`)."""


def run(args: argparse.Namespace) -> int:
    """Run ``svr simulate``."""
    from svr.sampling.simulate import SimulationConfig, simulate_case, write_case

    check_output_path(args.output_dir, args.overwrite)
    with option_errors(_OPTIONS):
        config = SimulationConfig(
            num_stacks=args.num_stacks,
            orientations=args.orientations,
            thickness_mm=args.thickness,
            spacing_mm=args.slice_spacing,
            in_plane_mm=args.in_plane_resolution,
            in_plane_psf=args.in_plane_psf,
            interleave=args.interleave,
            slice_time_s=args.slice_time,
            motion=args.motion.replace("-", "_"),
            motion_path=args.motion_path,
            motion_scale=args.motion_scale,
            random_walk_rotation_deg=args.rotation_deg,
            random_walk_translation_mm=args.translation_mm,
            noise=args.noise,
            bias_field=args.bias_field,
            signal_void_probability=args.signal_voids,
            random_placement=not args.no_random_placement,
            stack_turn_deg=(args.stack_turn_deg[0], args.stack_turn_deg[1]),
            seed=args.seed,
        )
    device = resolve_device(args.device)
    volume, source = load_input_volume(args)
    case = simulate_case(volume, config, progress=not args.quiet, device=device)
    out = write_case(case, args.output_dir, overwrite=args.overwrite, source=source)
    shapes = ", ".join("x".join(map(str, s.image.shape)) for s in case.stacks)
    print(f"wrote {out}: {len(case.stacks)} stacks ({shapes}) from {source}")
    return 0
