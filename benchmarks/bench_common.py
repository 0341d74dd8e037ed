"""Options shared by the benchmark scripts (run as ``python benchmarks/NAME.py``)."""

from __future__ import annotations

import argparse
import json
import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import torch

SHARED = Path(__file__).resolve().parents[2] / "shared"
ATLAS = SHARED / "data" / "atlas" / "sb-fidon2021"
MOTION = SHARED / "data" / "motion" / "svort_fetal_motion_trajectories.npz"
# FaBiAN's simulated stacks of normal brains (3 subjects) and their masks (one mask's name lacks
# the session); their world frame is the simulated brain's anatomical frame.
FABIAN = SHARED / "data" / "stacks" / "sim-fabian"
FABIAN_STACKS = {
    "sub-simu005_ses-01_run-2_T2w.nii.gz": "sub-simu005_ses-01_run-2_mask.nii.gz",
    "sub-simu005_ses-01_run-6_T2w.nii.gz": "sub-simu005_ses-01_run-6_mask.nii.gz",
    "sub-simu009_ses-01_run-7_T2w.nii.gz": "sub-simu009_run-7_mask.nii.gz",
    "sub-simu038_ses-01_run-2_T2w.nii.gz": "sub-simu038_ses-01_run-2_mask.nii.gz",
}


def write_results(path: Path, title: str, text: str, note: str = "") -> None:
    """Write a benchmark's markdown results: the title, the command that ran it, the text.

    Args:
        path: The results file (overwritten).
        title: Its heading.
        text: The body (tables, lines).
        note: Appended after the command (for example when and where it ran).
    """
    command = " ".join(["python", f"benchmarks/{Path(sys.argv[0]).name}", *sys.argv[1:]])
    path.write_text(f"# {title}\n\nCommand: `{command}`{note}\n\n{text}\n", encoding="utf-8")


def add_device_options(parser: argparse.ArgumentParser, cuda_note: str = "") -> None:
    """Add ``--threads`` (torch CPU threads, default 2) and ``--device cpu|cuda|all``."""
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    parser.add_argument(
        "--device",
        choices=["cpu", "cuda", "all"],
        default=None,
        help=f"default: cpu, plus cuda{cuda_note} when available",
    )


def resolve_devices(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list[str]:
    """Set the torch CPU threads and return the devices to measure.

    CUDA asked for but absent is a usage error (``parser.error``).
    """
    if args.device in ("cuda", "all") and not torch.cuda.is_available():
        parser.error("CUDA is not available")
    torch.set_num_threads(args.threads)
    if args.device is None:
        return ["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"]
    return ["cpu", "cuda"] if args.device == "all" else [args.device]


def true_slice_poses(
    slices: list[dict], frame: str, centre_mm: torch.Tensor | None = None
) -> torch.Tensor:
    """(K, 4, 4) float64 true poses of a stack's k-planes from a ``truth_slices.json`` entry.

    Args:
        slices: The entry's ``slices`` list (one per k-plane of the stack's file).
        frame: ``"scanner"`` (the ground-truth volume's world frame) or ``"atlas"`` (the
            source atlas's world frame).
        centre_mm: (3,) atlas brain-mask centre in mm; subtracted from the translations to give
            canonical poses (``DESIGN.md``). Only for ``frame="atlas"``.

    Returns:
        Poses mapping slice-plane mm (origin at the file's plane centre) to the frame, in mm.
    """
    from svr.sampling.simulate import pose_from_json

    poses = torch.stack([pose_from_json(s[frame]) for s in slices])
    if centre_mm is not None:
        poses[:, :3, 3] -= centre_mm.cpu().to(torch.float64)
    return poses


def run_scorer(scorer: Path, volume_path: Path, case: Path) -> dict[str, float]:
    """PSNR, SSIM and NCC of a volume against a case by the shared ``score_recon.py``."""
    output = subprocess.run(
        [sys.executable, str(scorer), str(volume_path), str(case)],
        capture_output=True,
        text=True,
        check=True,
    )
    return json.loads(output.stdout.strip().splitlines()[-1])


def load_case_stacks(case: Path) -> list:
    """The stacks of a case in the bench layout (``stacks/``, ``masks/``, ``case.json``)."""
    from svr.reconstruction.stacks import load_stacks

    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    paths = sorted((case / "stacks").glob("*.nii.gz"))
    masks = [case / "masks" / p.name.replace(".nii.gz", "_mask.nii.gz") for p in paths]
    return load_stacks(paths, masks, info["thickness"])


def reconstruct_default(stacks: list, registration: str, model=None):
    """``reconstruct`` with the defaults of ``--registration``; ``model`` is used for ``"cnn"``."""
    from svr.models.stack_pose import StackPoseNet
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.pipeline import reconstruct

    kind = {"none": "scanner", "stack": "stack", "atlas": "atlas"}.get(registration)
    if kind is None:
        kind = "learned" if isinstance(model, StackPoseNet) else "learned-slices"
    return reconstruct(
        stacks,
        ReconstructionConfig.preset(kind),
        model=model if registration == "cnn" else None,
        progress=False,
    )


def neighbour_atlas(age: float, offset: float = 1.0, atlas: Path = ATLAS) -> tuple[Path, Path]:
    """``(srr.nii.gz, mask.nii.gz)`` of the atlas age nearest ``age + offset`` other than ``age``.

    A case simulated from one atlas age is placed with a neighbouring age, as a user would use an
    atlas of about their fetus's age, never the very brain the case was made from.
    """
    from svr.sampling.volume import atlas_volume_paths

    pairs = atlas_volume_paths(atlas)
    ages = [float(v.parent.name[2:4]) for v, _ in pairs]
    target = age + offset
    index = min(
        (i for i, a in enumerate(ages) if a != age), key=lambda i: (abs(ages[i] - target), ages[i])
    )
    return pairs[index]


def case_age(case: Path) -> float:
    """The atlas age (weeks) a bench or simulated case was made from (its ``case.json``)."""
    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    source = str(info.get("source", ""))
    at = source.find("GA")
    if at < 0:
        raise ValueError(f"{case}/case.json: no GA<weeks> in its source {source!r}")
    return float(source[at + 2 : at + 4])


def simulate_cases(
    folder: Path, specs: dict[str, tuple[str, str, float, int, int] | tuple]
) -> list[Path]:
    """Simulate cases into ``folder`` (kept between runs) with ``svr simulate``.

    Args:
        folder: Where the case folders go (bench layout: ``stacks/``, ``masks/``, ``case.json``,
            ground truth).
        specs: Case name -> (atlas age folder under ``ATLAS``, stack orientations, scale of the
            real fetal motion trajectories, number of stacks, seed[, (low, high) degrees the
            fetus turns between stacks]). Thickness 3 mm, bias field 0.2.

    Returns:
        The case folders, in the order of ``specs``.
    """
    out = []
    folder.mkdir(parents=True, exist_ok=True)
    for name, spec in specs.items():
        age, orientations, scale, stacks, seed = spec[:5]
        turn = [str(a) for a in spec[5]] if len(spec) > 5 else ["0", "0"]
        case = folder / name
        if not (case / "case.json").exists():
            subprocess.run(
                [
                    sys.executable, "-m", "svr", "simulate",
                    "--output-dir", str(case),
                    "--input-volume", str(ATLAS / age / "srr.nii.gz"),
                    "--input-mask", str(ATLAS / age / "mask.nii.gz"),
                    "--num-stacks", str(stacks),
                    "--orientations", orientations,
                    "--thickness", "3",
                    "--motion", "trajectories",
                    "--motion-path", str(MOTION),
                    "--motion-scale", str(scale),
                    "--bias-field", "0.2",
                    "--stack-turn-deg", *turn,
                    "--seed", str(seed),
                    "--device", "cpu",
                    "--quiet",
                ],
                check=True,
            )  # fmt: skip
        out.append(case)
    return out


def scanner_from_canonical(transforms: Path) -> np.ndarray:
    """(4, 4) ``G``: the stacks' scanner frame as a canonical-frame output's slices see it.

    ``G = robust_mean_pose(S_i o P_i^-1)`` over the slices that were not excluded, with ``S_i``
    the scanner pose of the slice's k-plane in its file and ``P_i`` its final canonical pose from
    the transforms table: canonical mm -> scanner mm, up to each stack's own motion. This, not a
    canonical output's affine, is its frame: the affine maps voxels to canonical mm on a grid
    built in the frame the slices had before the output was turned onto an atlas or levelled, so
    its rotation is only those last turns.

    Args:
        transforms: A canonical-frame ``--output-transforms`` table (``.csv``).

    Returns:
        float64 ``G``.
    """
    import csv

    from svr.geometry import se3_compose, se3_inverse, vector_to_se3
    from svr.geometry.averaging import robust_mean_pose
    from svr.image import load_nifti, stack_slice_poses
    from svr.pose_io import read_pose_table

    table = read_pose_table(transforms)
    with transforms.open(newline="") as f:
        kept = [row.get("excluded", "False") != "True" for row in csv.DictReader(f)]
    planes = {name: stack_slice_poses(load_nifti(name)) for name in dict.fromkeys(table.files)}
    scanner = torch.stack(
        [planes[f][int(k)] for f, k in zip(table.files, table.slice_indices.tolist(), strict=True)]
    )
    canonical = vector_to_se3(table.poses)
    use = torch.tensor(kept)
    return robust_mean_pose(se3_compose(scanner[use], se3_inverse(canonical[use]))).numpy()


def scanner_frame_copy(volume: Path, transforms: Path, out: Path) -> Path:
    """Write ``volume`` (in the canonical frame) relabelled into the stacks' scanner frame.

    The shared yardstick registers a reconstruction to the ground truth from a set of start
    orientations, and its score depends on the orientation the volume comes in: the same array
    with only its affine turned by a rigid transform scored up to 2.8 dB lower on sb24-large
    (``benchmarks/results/frame-equivariance.md``). A canonical-frame output is therefore
    also scored in the scanner frame, without resampling: its affine is premultiplied by
    :func:`scanner_from_canonical`, the scanner frame as the slices see it, which is the frame a
    ``--registration stack`` run outputs in up to the template stack's own motion.

    Args:
        volume: The canonical-frame volume (NIfTI).
        transforms: Its ``--output-transforms`` table (``.csv``).
        out: Where to write the copy.

    Returns:
        ``out``.
    """
    import nibabel as nib

    image = nib.load(volume)
    frame = scanner_from_canonical(transforms)
    relabelled = nib.Nifti1Image(np.asarray(image.dataobj), frame @ image.affine)
    nib.save(relabelled, out)
    return out


VERDICT_LINE = re.compile(r"verdict: (.+)$", re.MULTILINE)


def verdict_in(text: str) -> str:
    """The last verdict an ``svr reconstruct`` log (``-v`` or ``--output-log``) states, or ""."""
    found = VERDICT_LINE.findall(text)
    return found[-1] if found else ""


def true_frame_correction(case: Path, transforms: Path) -> torch.Tensor:
    """(4, 4) float64 transform from a canonical-frame output's frame to the true atlas frame.

    The robust mean over the transforms table's slices of ``T_i o P_i^-1``, with ``T_i`` the
    slice's true canonical pose (``truth_slices.json``, atlas frame minus the atlas centre) and
    ``P_i`` its final pose.
    """
    from svr.geometry import se3_compose, se3_inverse, vector_to_se3
    from svr.geometry.averaging import robust_mean_pose
    from svr.pose_io import read_pose_table

    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    centre = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_name = {Path(s["file"]).name: s["slices"] for s in truth}
    table = read_pose_table(transforms)
    per_file = {
        name: true_slice_poses(by_name[Path(name).name], "atlas", centre)
        for name in dict.fromkeys(table.files)
    }
    true = torch.stack(
        [
            per_file[f][int(k)]
            for f, k in zip(table.files, table.slice_indices.tolist(), strict=True)
        ]
    )
    return robust_mean_pose(se3_compose(true, se3_inverse(vector_to_se3(table.poses))))


def output_frame_error(case: Path, transforms: Path) -> tuple[float, float]:
    """How far a canonical-frame output is from the true atlas frame: degrees and mm.

    The rotation angle of :func:`true_frame_correction` and its translation (at the canonical
    origin, the brain's centre).
    """
    from svr.geometry import rotation_angle

    mean = true_frame_correction(case, transforms)
    turn = math.degrees(rotation_angle(mean, torch.eye(4, dtype=mean.dtype)))
    return turn, float(mean[:3, 3].norm())


def slice_pose_errors(case: Path, transforms: Path) -> dict[str, float]:
    """Every slice's pose error against the case's truth, after one rigid offset of the frame.

    The table's poses are moved by the robust mean of ``T_i o P_i^-1`` (``T_i`` the slice's true
    pose in the table's frame: the atlas frame for a canonical table, the ground truth's world
    frame for a scanner one; ``P_i`` its pose in the table), so that what is left is each slice's
    own error, not the frame's.

    Returns:
        ``median_deg``, ``p90_deg``, ``within_5`` and ``within_10`` (percent of slices within 5 and
        10 degrees) and ``median_mm`` (slice centres).
    """
    from svr.geometry import rotation_angle, se3_compose, se3_inverse, vector_to_se3
    from svr.geometry.averaging import robust_mean_pose
    from svr.pose_io import read_pose_table

    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
    by_name = {Path(s["file"]).name: s["slices"] for s in truth}
    table = read_pose_table(transforms)
    frame = "scanner" if table.frame == "scanner" else "atlas"
    per_file = {
        name: true_slice_poses(by_name[Path(name).name], frame)
        for name in dict.fromkeys(table.files)
    }
    true = torch.stack(
        [
            per_file[f][int(k)]
            for f, k in zip(table.files, table.slice_indices.tolist(), strict=True)
        ]
    )
    estimate = vector_to_se3(table.poses.double())
    offset = robust_mean_pose(se3_compose(true, se3_inverse(estimate)))
    aligned = se3_compose(offset[None], estimate)
    angle = torch.rad2deg(rotation_angle(aligned, true))
    distance = (aligned[:, :3, 3] - true[:, :3, 3]).norm(dim=1)
    return {
        "median_deg": float(angle.median()),
        "p90_deg": float(angle.quantile(0.9)),
        "within_5": 100.0 * float((angle <= 5).double().mean()),
        "within_10": 100.0 * float((angle <= 10).double().mean()),
        "median_mm": float(distance.median()),
    }
