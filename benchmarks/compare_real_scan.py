"""Compare our reconstruction of a real clinical scan with MIALSRTK's, by slice consistency.

What it measures. There is no ground truth for a real scan, so the two volumes are compared by
how well each explains the acquired data: every observed slice (the stacks prepared as
``svr reconstruct`` prepares them: given brain masks, 5 mm in-plane crop margin, no bias
correction, intensities over the in-mask 99th percentile) is compared, by NCC over its masked
pixels, with the slice simulated from a volume through the acquisition model
(:class:`svr.reconstruction.operators.SliceProjector`: Gaussian PSF, 5 nodes along the normal, the
same operator and NCC as the reconstruction's own ``ncc`` column) at **our** final slice poses
(the transforms table). The volumes:

* ours: the ``svr reconstruct`` output (scanner frame);
* MIALSRTK: the dataset's TV super-resolution (``sub-01_rec-SR_id-1``), rigidly registered to
  ours with SimpleITK (Euler3D, moments initialisation, correlation metric over every voxel of
  ``ours > 0``, shrink 4/2/1; the 24 axis-permutation start rotations are tried if the identity
  start ends below ``--min-correlation`` in volume NCC) and resampled (trilinear) onto our grid.

To see how much of the gap is our poses imposed on MIALSRTK, the slices are also registered
once more to each volume (one slice-to-volume pass from our poses: the reconstruction's own step,
:func:`svr.reconstruction.pipeline.svr_pass`, with its default settings: every slice alone,
3 levels of 6 Levenberg-Marquardt steps, slices under 200 pixels fixed; the common motion is not
taken back out, the volume being fixed) and the NCC recomputed at those poses ("slices
re-registered" rows).

It also shows both volumes side by side (orthogonal planes through our mask's centroid, our
mask's outline drawn on both) and the per-slice NCCs of both methods.

Caveats (read the numbers with these in mind):

* The comparison favours ours. Our volume was fitted to exactly these slices at exactly these
  poses (its NCC is the training-set fit), and ``ours > 0`` is our coverage mask. MIALSRTK
  estimated its own slice motion with its own preprocessing (automatic masks, per its sidecar,
  and its own intensity handling) and used only the runs listed in its sidecar (6, 3, 1);
  its volume is sampled here at our poses, so our motion estimate is imposed on it. Numbers are
  therefore given separately for MIALSRTK's input runs and for the others, which it never saw.
* MIALSRTK's volume is masked by its own brain mask: where our slice masks reach beyond it the
  simulated slice is zero there, which lowers its NCC. The "common support" rows keep only the
  pixels whose whole PSF footprint lies inside both volumes' supports (``> 0``).
* One rigid transform aligns the two volumes; residual misregistration (and the trilinear
  resampling of MIALSRTK's 1.125 mm grid onto our 0.8 mm grid) costs MIALSRTK a little.
* MIALSRTK's volume is visibly smoother than ours; a smoother volume simulates slices that
  are smoother than the observed ones, which this measure penalises (rightly, as a loss of
  detail the data support, but some of it is a choice of regularisation strength).
* NCC is invariant to each slice's linear intensity map, so intensity scales do not matter;
  the figure's linear intensity fit is for display only.

Checks printed and stored: the pose conversion round-trips on the scanner poses; the posed
slices reproduce the run's slice folder (affines and pixels); our recomputed NCC matches the
table's ``ncc`` column up to the volume's final coverage mask (applied after that column was
computed) and float32 storage.

Run from the repository root (about 20 s on one thread)::

    OMP_NUM_THREADS=1 python benchmarks/compare_real_scan.py \
        --stacks-dir ../shared/data/stacks/real-mialsrtk-sub01 \
        --ours runs/recon/real.nii.gz --transforms runs/recon/real.csv \
        --reference ../shared/data/stacks/real-mialsrtk-sub01/sub-01_rec-SR_id-1_T2w.nii.gz \
        --slices-dir runs/recon/real-slices \
        --out runs/recon/real-vs-mialsrtk.png --json runs/recon/real-vs-mialsrtk.json
"""

from __future__ import annotations

import argparse
import csv
import io
import itertools
import json
import re
import sys
import time
from pathlib import Path

import numpy as np
import SimpleITK as sitk  # noqa: N813 (the usual alias)
import torch
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from torch import Tensor

from svr import image_metrics
from svr.files import atomic_write_bytes, atomic_write_text, check_output_path
from svr.geometry import vector_to_se3
from svr.image import Image, load_nifti
from svr.pose_io import read_pose_table
from svr.reconstruction.acquisition import acquisition_model
from svr.reconstruction.config import ReconstructionConfig
from svr.reconstruction.operators import VolumeGrid
from svr.reconstruction.outputs import slice_affines
from svr.reconstruction.qa import orthogonal_planes
from svr.reconstruction.registration import slice_ncc
from svr.reconstruction.rounds import svr_pass
from svr.reconstruction.slices import SliceSet, array_poses, extract_slices, plane_poses
from svr.reconstruction.stacks import load_stacks

_LPS = np.diag([-1.0, -1.0, 1.0])  # RAS <-> LPS (ITK's world frame)
_RUN = re.compile(r"run-(\d+)")
_SUPPORT_LEVEL = 0.999  # a pixel's blurred support indicator must reach this (whole PSF inside)
_RECONSTRUCTION = ReconstructionConfig()  # its defaults: the SVR settings used here


def _run_of(name: str) -> int:
    match = _RUN.search(Path(name).name)
    if match is None:
        raise ValueError(f"{name}: no 'run-<n>' in the file name")
    return int(match.group(1))


# ---------------------------------------------------------------------------------------------
# Slices at the table's poses


def stack_files(stacks_dir: Path) -> tuple[list[Path], list[Path]]:
    """The ``*_run-<n>_T2w.nii.gz`` stacks of a folder (by run) and their brain masks."""
    stacks = sorted(stacks_dir.glob("*_run-*_T2w.nii.gz"), key=lambda p: _run_of(p.name))
    if not stacks:
        raise FileNotFoundError(f"{stacks_dir}: no *_run-*_T2w.nii.gz stacks")
    masks = [
        p.with_name(p.name.replace("_T2w.nii.gz", "_T2w_desc-brain_mask.nii.gz")) for p in stacks
    ]
    for mask in masks:
        if not mask.exists():
            raise FileNotFoundError(f"{mask}: brain mask missing")
    return stacks, masks


def read_transforms(path: Path) -> tuple[dict[tuple[str, int], int], Tensor, str, list[dict]]:
    """The pose table: (file name, k) -> row, (N, 4, 4) plane poses, frame, and the raw rows.

    The poses come from :func:`read_pose_table` (its 6-vectors are authoritative); the extra
    columns (``ncc``, ``weight``, ``excluded``), which it ignores, from the CSV rows.
    """
    table = read_pose_table(path)
    with path.open(newline="") as f:
        rows = list(csv.DictReader(f))
    keys = {
        (Path(name).name, int(k)): row
        for row, (name, k) in enumerate(zip(table.files, table.slice_indices.tolist(), strict=True))
    }
    if len(keys) != len(rows):
        raise ValueError(f"{path}: repeated (file, slice_index) rows")
    return keys, vector_to_se3(table.poses), table.frame, rows


def posed_slices(
    stacks_dir: Path, transforms: Path, thickness: float
) -> tuple[SliceSet, np.ndarray, dict[str, float]]:
    """The slices posed from the transforms table, the table row of each, and the checks.

    Raises:
        ValueError: If the table's slices are not exactly the extracted ones, or the pose
            conversion does not round-trip on the scanner poses.
    """
    stack_paths, mask_paths = stack_files(stacks_dir)
    slices = extract_slices(load_stacks(stack_paths, mask_paths, thicknesses=thickness))
    keys, planes, frame, _ = read_transforms(transforms)
    names = [Path(n).name for n in slices.stack_names]
    ours = [
        (names[int(s)], int(k))
        for s, k in zip(slices.stack_ids.tolist(), slices.slice_indices.tolist(), strict=True)
    ]
    missing = [key for key in ours if key not in keys]
    if missing or len(ours) != len(keys):
        raise ValueError(
            f"{transforms}: its {len(keys)} slices are not the {len(ours)} extracted from "
            f"{stacks_dir} (first missing: {missing[:3]})"
        )
    order = np.array([keys[key] for key in ours])
    # Round trip on the scanner poses: plane_poses then its inverse gives them back.
    scanner = slices.scanner_poses.to(torch.float64)
    back = array_poses(slices, plane_poses(slices, scanner))
    round_trip = float((back - scanner).abs().max())
    if round_trip > 1e-9:
        raise ValueError(f"plane pose round trip is off by {round_trip:.3g} mm")
    poses = array_poses(slices, planes[torch.from_numpy(order)])
    posed = slices.with_poses(poses, "scanner" if frame == "scanner" else "canonical")
    checks = {
        "frame": frame,
        "round_trip_max_abs": round_trip,
        "table_round_trip_max_abs": float(
            (plane_poses(posed)[:, :3] - planes[torch.from_numpy(order)][:, :3]).abs().max()
        ),
    }
    return posed, order, checks


def check_slice_folder(slices: SliceSet, order: np.ndarray, folder: Path) -> dict[str, float]:
    """Compare the posed slices with the run's NeSVoR slice folder (file n = table row n)."""
    affines = slice_affines(slices)
    worst_affine, worst_pixel, count = 0.0, 0.0, 0
    for n, row in enumerate(order.tolist()):
        path = folder / f"{row}.nii.gz"
        if not path.exists():  # excluded slices may be left out
            continue
        written = load_nifti(path, torch.float64)
        worst_affine = max(worst_affine, float((written.affine - affines[n]).abs().max()))
        pixels = slices.images[n].double() - written.data[:, :, 0]
        worst_pixel = max(worst_pixel, float(pixels.abs().max()))
        count += 1
    return {
        "slice_folder_files": count,
        "slice_folder_affine_max_abs": worst_affine,
        "slice_folder_pixel_max_abs": worst_pixel,
    }


# ---------------------------------------------------------------------------------------------
# Rigid registration of the reference to ours (SimpleITK)


def to_sitk(image: Image) -> sitk.Image:
    """An RAS :class:`Image` as a SimpleITK image (LPS world, same voxels)."""
    affine = image.affine.double().numpy()
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    direction = _LPS @ affine[:3, :3] / spacing
    u, _, vt = np.linalg.svd(direction)  # exactly orthonormal (NIfTI rounding)
    out = sitk.GetImageFromArray(image.data.float().numpy().T.copy())
    out.SetSpacing(spacing.tolist())
    out.SetDirection((u @ vt).ravel().tolist())
    out.SetOrigin((_LPS @ affine[:3, 3]).tolist())
    return out


def _axis_rotations() -> list[np.ndarray]:
    """The 24 proper rotations that permute and flip the axes (identity first)."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    out.sort(key=lambda R: -np.trace(R))
    return out


def _masked_ncc(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """NCC of two volumes inside a mask (:func:`svr.image_metrics.ncc` on one flattened slice)."""
    a_, b_, m_ = (torch.from_numpy(np.ascontiguousarray(x)).reshape(1, 1, -1) for x in (a, b, mask))
    return float(image_metrics.ncc(a_.double(), b_.double(), m_.bool())[0])


def _register(
    fixed: sitk.Image,
    moving: sitk.Image,
    mask: sitk.Image,
    initial: sitk.Euler3DTransform,
    shrink: list[int],
    iterations: int,
) -> sitk.Euler3DTransform:
    method = sitk.ImageRegistrationMethod()
    method.SetMetricAsCorrelation()
    method.SetMetricFixedMask(mask)
    # Every voxel in the mask: ITK's seeded random sampling still varies from run to run.
    method.SetMetricSamplingStrategy(method.NONE)
    method.SetInterpolator(sitk.sitkLinear)
    method.SetOptimizerAsRegularStepGradientDescent(
        learningRate=2.0, minStep=1e-3, numberOfIterations=iterations, relaxationFactor=0.6
    )
    method.SetOptimizerScalesFromPhysicalShift()
    method.SetShrinkFactorsPerLevel(shrink)
    method.SetSmoothingSigmasPerLevel([max(s - 1, 0) for s in shrink])
    method.SetSmoothingSigmasAreSpecifiedInPhysicalUnits(False)
    method.SetInitialTransform(sitk.Euler3DTransform(initial), inPlace=False)
    out = method.Execute(fixed, moving)
    return sitk.Euler3DTransform(
        out.GetNthTransform(0) if out.GetName() == "CompositeTransform" else out
    )


def register_reference(
    ours: Image, reference: Image, min_correlation: float
) -> tuple[Image, dict[str, object]]:
    """Register ``reference`` rigidly to ``ours`` and resample it onto our grid (trilinear)."""
    fixed, moving = to_sitk(ours), to_sitk(reference)
    inside = ours.data.numpy() > 0
    mask = sitk.GetImageFromArray(inside.T.astype(np.uint8).copy())
    mask.CopyInformation(fixed)
    start = sitk.CenteredTransformInitializer(
        fixed, moving, sitk.Euler3DTransform(), sitk.CenteredTransformInitializerFilter.MOMENTS
    )
    start = sitk.Euler3DTransform(start)

    def resampled(transform: sitk.Transform) -> np.ndarray:
        out = sitk.Resample(moving, fixed, transform, sitk.sitkLinear, 0.0, sitk.sitkFloat32)
        return sitk.GetArrayFromImage(out).T

    def started(R: np.ndarray) -> sitk.Euler3DTransform:
        t = sitk.Euler3DTransform(start)
        t.SetMatrix(R.ravel().tolist())
        return t

    rotations = _axis_rotations()
    best = _register(fixed, moving, mask, started(rotations[0]), [4, 2, 1], 200)
    best_ncc = _masked_ncc(ours.data.numpy(), resampled(best), inside)
    tried = [{"start": "identity", "ncc": best_ncc}]
    if best_ncc < min_correlation:
        coarse = []
        for n, R in enumerate(rotations):
            t = _register(fixed, moving, mask, started(R), [4], 40)
            ncc = _masked_ncc(ours.data.numpy(), resampled(t), inside)
            coarse.append((ncc, n, t))
            tried.append({"start": f"axis rotation {n}", "coarse_ncc": ncc})
        ncc, n, t = max(coarse, key=lambda c: c[0])
        refined = _register(fixed, moving, mask, t, [4, 2, 1], 200)
        refined_ncc = _masked_ncc(ours.data.numpy(), resampled(refined), inside)
        tried.append({"start": f"axis rotation {n} refined", "ncc": refined_ncc})
        if refined_ncc > best_ncc:
            best, best_ncc = refined, refined_ncc
    matrix = np.array(best.GetMatrix()).reshape(3, 3)
    angle = float(np.degrees(np.arccos(np.clip((np.trace(matrix) - 1) / 2, -1, 1))))
    data = np.ascontiguousarray(resampled(best))
    info = {
        "volume_ncc_in_our_mask": best_ncc,
        "volume_ncc_in_both_supports": _masked_ncc(ours.data.numpy(), data, inside & (data > 0)),
        "rotation_deg": angle,
        "translation_mm_lps": list(best.GetTranslation()),
        "centre_mm_lps": list(best.GetCenter()),
        "starts": tried,
    }
    return Image(torch.from_numpy(data).float(), ours.affine.clone()), info


# ---------------------------------------------------------------------------------------------
# Slice consistency


def consistency(slices: SliceSet, ours: Image, reference: Image) -> dict[str, np.ndarray]:
    """Per-slice NCC of observed vs simulated slices, from ours and the reference.

    Returns:
        ``ours`` and ``reference``: NCC over all masked pixels at the given poses;
        ``ours_support`` and ``reference_support``: over the common support, with
        ``support_pixels`` per slice; ``ours_svr`` and ``reference_svr``: at poses re-registered
        to each volume by one slice-to-volume pass from the given poses.
    """
    acquisition = acquisition_model(slices, VolumeGrid(ours.shape, ours.affine.double()))
    projector, observed = acquisition.projector, acquisition.observed
    points = acquisition.points(slices.poses)
    volumes = {"ours": ours.data.float(), "reference": reference.data.float()}
    support = ((ours.data > 0) & (reference.data > 0)).float()
    out = {}
    with torch.no_grad():
        inside = projector.forward(support, points) >= _SUPPORT_LEVEL
        pixels = torch.nonzero(inside).flatten()
        out["support_pixels"] = (
            torch.zeros(len(slices))
            .index_add(0, projector.slice_of[pixels], torch.ones(len(pixels)))
            .numpy()
        )
        for name, volume in volumes.items():
            simulated = projector.forward(volume, points)
            out[name] = slice_ncc(projector, simulated, observed).double().numpy()
            out[f"{name}_support"] = (
                slice_ncc(projector, simulated[pixels], observed[pixels], pixels).double().numpy()
            )
    # The reconstruction's last SVR pass: every slice its own group, slices with little brain
    # fixed; not anchored (the volume does not move here).
    for name, volume in volumes.items():
        poses = svr_pass(acquisition, volume, slices.poses, _RECONSTRUCTION, anchor=False)
        with torch.no_grad():
            simulated = projector.forward(volume, acquisition.points(poses))
            out[f"{name}_svr"] = slice_ncc(projector, simulated, observed).double().numpy()
    return out


def summary(ours: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    return {
        "slices": len(ours),
        "ours_mean": float(np.mean(ours)),
        "ours_median": float(np.median(ours)),
        "reference_mean": float(np.mean(ref)),
        "reference_median": float(np.median(ref)),
        "fraction_ours_higher": float(np.mean(ours > ref)),
    }


# ---------------------------------------------------------------------------------------------
# Figure


def figure(
    path: Path,
    ours: Image,
    reference: Image,
    ncc_ours: np.ndarray,
    ncc_ref: np.ndarray,
    runs: np.ndarray,
    reference_runs: list[int],
    caption: str,
    overwrite: bool,
) -> Path:
    a = ours.data.numpy().astype(np.float64)
    b = reference.data.numpy().astype(np.float64)
    mask = a > 0
    both = mask & (b > 0)
    slope, intercept = np.polyfit(b[both], a[both], 1)
    b_display = np.where(b > 0, np.clip(slope * b + intercept, 0, None), 0.0)
    centre = tuple(round(float(c)) for c in np.argwhere(mask).mean(axis=0))
    affine = ours.affine.double().numpy()
    world = affine[:3, :3] @ np.array(centre, dtype=np.float64) + affine[:3, 3]
    vmax = float(np.percentile(a[mask], 99.5))

    fig = Figure(figsize=(10.0, 10.5), layout="constrained")
    FigureCanvasAgg(fig)
    grid = fig.add_gridspec(4, 3, height_ratios=[1.0, 1.0, 1.15, 0.42])
    titles = ("sagittal", "coronal", "axial")
    for row, (name, data) in enumerate(
        (
            ("ours", a),
            (f"MIALSRTK (runs {', '.join(map(str, reference_runs))}), registered", b_display),
        )
    ):
        for col, (plane, outline) in enumerate(
            zip(
                orthogonal_planes(data, centre),
                orthogonal_planes(mask.astype(float), centre),
                strict=True,
            )
        ):
            ax = fig.add_subplot(grid[row, col])
            ax.imshow(plane, cmap="gray", origin="lower", vmin=0.0, vmax=vmax)
            ax.contour(outline, levels=[0.5], colors="tab:orange", linewidths=0.6, origin="lower")
            ax.set_xticks([])
            ax.set_yticks([])
            if col == 0:
                ax.set_ylabel(name, fontsize=9)
            if row == 0:
                ax.set_title(f"{titles[col]}, {'xyz'[col]} = {world[col]:.1f} mm (RAS)", fontsize=9)

    ax = fig.add_subplot(grid[2, :2])
    lo = float(min(ncc_ours.min(), ncc_ref.min())) - 0.02
    for run in np.unique(runs):
        sel = runs == run
        marker = "o" if run in reference_runs else "^"
        used = "MIALSRTK input" if run in reference_runs else "not in MIALSRTK"
        ax.plot(ncc_ref[sel], ncc_ours[sel], marker, ms=4, label=f"run {run} ({used})")
    ax.plot([lo, 1], [lo, 1], "k--", lw=0.8)
    ax.set_xlim(lo, 1.0)
    ax.set_ylim(lo, 1.0)
    ax.set_xlabel("slice NCC, simulated from MIALSRTK")
    ax.set_ylabel("slice NCC, simulated from ours")
    ax.set_title("per-slice NCC at our slice poses (above the line: ours fits better)", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")

    ax = fig.add_subplot(grid[2, 2])
    bins = np.linspace(lo, 1.0, 30)
    ax.hist(ncc_ours, bins=bins, alpha=0.6, label="ours")
    ax.hist(ncc_ref, bins=bins, alpha=0.6, label="MIALSRTK")
    ax.set_xlabel("slice NCC (all runs)")
    ax.set_ylabel("slices")
    ax.legend(fontsize=7)

    ax = fig.add_subplot(grid[3, :])
    ax.axis("off")
    ax.text(0.0, 1.0, caption, va="top", ha="left", family="monospace", fontsize=7.5)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100)
    return atomic_write_bytes(path, buffer.getvalue(), overwrite)


# ---------------------------------------------------------------------------------------------


def _reference_runs(reference: Path, given: str | None) -> list[int]:
    if given:
        return [int(r) for r in given.split(",")]
    sidecar = Path(str(reference).removesuffix(".gz").removesuffix(".nii") + ".json")
    try:
        return [int(r) for r in json.loads(sidecar.read_text())["Input sources run order"]]
    except (OSError, KeyError, ValueError) as err:
        raise ValueError(f"{sidecar}: no 'Input sources run order'; pass --reference-runs") from err


def markdown(rows: list[tuple[str, dict[str, float]]]) -> str:
    lines = [
        "| slices | n | ours mean | ours median | MIALSRTK mean | MIALSRTK median | ours higher |",
        "|---|---:|---:|---:|---:|---:|---:|",
    ]
    for name, s in rows:
        lines.append(
            f"| {name} | {s['slices']} | {s['ours_mean']:.4f} | {s['ours_median']:.4f} | "
            f"{s['reference_mean']:.4f} | {s['reference_median']:.4f} | "
            f"{100 * s['fraction_ours_higher']:.0f}% |"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--stacks-dir", type=Path, required=True)
    parser.add_argument("--ours", type=Path, default=Path("runs/recon/real.nii.gz"))
    parser.add_argument("--transforms", type=Path, default=Path("runs/recon/real.csv"))
    parser.add_argument("--reference", type=Path, required=True, help="MIALSRTK volume")
    parser.add_argument(
        "--reference-runs", help="runs MIALSRTK used, e.g. 6,3,1 (default: from its sidecar)"
    )
    parser.add_argument(
        "--slices-dir", type=Path, help="the run's slice folder, checked against the posed slices"
    )
    parser.add_argument("--thickness", type=float, default=3.0)
    parser.add_argument(
        "--min-correlation",
        type=float,
        default=0.5,
        help="volume NCC below which the 24 axis-rotation starts are tried (1 to always try)",
    )
    parser.add_argument("--out", type=Path, default=Path("runs/recon/real-vs-mialsrtk.png"))
    parser.add_argument("--json", type=Path, default=Path("runs/recon/real-vs-mialsrtk.json"))
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    check_output_path(args.out, args.overwrite)
    check_output_path(args.json, args.overwrite)
    sitk.ProcessObject.SetGlobalDefaultNumberOfThreads(torch.get_num_threads())
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = now - clock
        clock = now

    reference_runs = _reference_runs(args.reference, args.reference_runs)
    slices, order, checks = posed_slices(args.stacks_dir, args.transforms, args.thickness)
    if args.slices_dir is not None:
        checks.update(check_slice_folder(slices, order, args.slices_dir))
    lap("slices")
    ours = load_nifti(args.ours)
    registered, registration = register_reference(
        ours, load_nifti(args.reference), args.min_correlation
    )
    lap("registration")
    ncc = consistency(slices, ours, registered)
    ncc_ours, ncc_ref = ncc["ours"], ncc["reference"]
    _, _, _, rows = read_transforms(args.transforms)
    table_ncc = np.array([float(rows[r]["ncc"]) for r in order])
    checks["ncc_vs_table_max_abs"] = float(np.abs(ncc_ours - table_ncc).max())
    checks["ncc_vs_table_mean_abs"] = float(np.abs(ncc_ours - table_ncc).mean())
    lap("consistency")

    runs = np.array([_run_of(slices.stack_names[int(s)]) for s in slices.stack_ids.tolist()])
    used = np.isin(runs, reference_runs)
    ok = ncc["support_pixels"] >= 50  # common-support NCC only where enough pixels remain
    subsets = [
        (f"runs {','.join(map(str, reference_runs))} (MIALSRTK inputs)", used),
        ("other runs (not in MIALSRTK)", ~used),
        ("all runs", np.ones_like(used)),
    ]
    table_rows = [(name, summary(ncc_ours[sel], ncc_ref[sel])) for name, sel in subsets]
    table_rows += [
        (
            f"{name}, common support",
            summary(ncc["ours_support"][sel & ok], ncc["reference_support"][sel & ok]),
        )
        for name, sel in subsets
    ]
    table_rows += [
        (f"{name}, slices re-registered", summary(ncc["ours_svr"][sel], ncc["reference_svr"][sel]))
        for name, sel in subsets
    ]
    table_rows += [
        (f"run {run}", summary(ncc_ours[runs == run], ncc_ref[runs == run]))
        for run in sorted(set(runs.tolist()))
    ]
    text = markdown(table_rows)
    reg_line = (
        f"registration: volume NCC in our mask {registration['volume_ncc_in_our_mask']:.3f}, "
        f"rotation {registration['rotation_deg']:.1f} deg, "
        f"{len(registration['starts'])} start(s)"
    )
    head = {name: s for name, s in table_rows[:9] if "common support" not in name}
    caption = "\n".join(
        [
            "Slice NCC (masked pixels) of observed slices vs slices simulated (PSF) at our poses,",
            "or at poses re-registered to each volume (one slice-to-volume pass):",
            *(
                f"  {name:<54} n={s['slices']:3d}  ours {s['ours_mean']:.3f} "
                f"(median {s['ours_median']:.3f})  MIALSRTK {s['reference_mean']:.3f} "
                f"(median {s['reference_median']:.3f})  ours higher "
                f"{100 * s['fraction_ours_higher']:.0f}%"
                for name, s in head.items()
            ),
            reg_line + "; MIALSRTK shown after a linear intensity fit to ours (display only).",
            "Caveat: our volume was fitted to these slices at these poses; MIALSRTK used its own "
            "motion estimates, preprocessing and only its input runs.",
        ]
    )
    figure(
        args.out,
        ours,
        registered,
        ncc_ours,
        ncc_ref,
        runs,
        reference_runs,
        caption,
        args.overwrite,
    )
    lap("figure")
    report = {
        "inputs": {
            "stacks_dir": str(args.stacks_dir),
            "ours": str(args.ours),
            "transforms": str(args.transforms),
            "reference": str(args.reference),
            "reference_runs": reference_runs,
            "thickness_mm": args.thickness,
        },
        "checks": checks,
        "registration": registration,
        "summary": {name: s for name, s in table_rows},
        "per_slice": [
            {
                "table_row": int(row),
                "run": int(runs[n]),
                "k": int(slices.slice_indices[n]),
                **{
                    f"ncc_{key}": float(values[n])
                    if ok[n] or not key.endswith("_support")
                    else None
                    for key, values in ncc.items()
                    if key != "support_pixels"
                },
                "support_pixels": int(ncc["support_pixels"][n]),
            }
            for n, row in enumerate(order.tolist())
        ],
        "timings_s": timings,
    }
    atomic_write_text(args.json, json.dumps(report, indent=1) + "\n", args.overwrite)
    print(text)
    print()
    print(reg_line)
    print(
        "checks: "
        + ", ".join(
            f"{k} {v:.3g}" if isinstance(v, float) else f"{k} {v}" for k, v in checks.items()
        )
    )
    print("time (s): " + ", ".join(f"{k} {v:.1f}" for k, v in timings.items()))
    print(f"wrote {args.out} and {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
