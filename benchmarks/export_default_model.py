r"""Export the shipped slice-pose model (``models/pretrained/default``) and evaluate it.

Run from the repository root once the training command :data:`TRAINING_COMMAND` has finished::

    python benchmarks/export_default_model.py \
        --checkpoint runs/sym-heldout/checkpoints/step_000032000 \
        --out models/pretrained/default --overwrite

Steps:
    1. :func:`svr.models.pretrained.export.export_model`: float16 safetensors + JSON config with the
       provenance (the exact training command, the data and its licence, steps, versions).
    2. The *exported* model (loaded back, as ``svr predict --model default`` loads it) is
       evaluated:

       * on anatomy it has not seen, the built-in procedural phantom at several gestational ages
         (``--phantom-ga``): ``--num-slices`` slices per volume, ``--thickness`` mm thick, at
         random poses (a) in the paper's Euler box (angles in +-90 deg, offsets in +-40 mm) and
         (b) with uniform rotations on SO(3) (offsets in +-40 mm), that pass the empty-slice rule
         (:func:`svr.sampling.poses.draw_validation_poses`);
       * the same on the atlas volumes training held out (``--num-slices`` each) and, for
         reference, on the training atlas volumes (seen anatomy, ``--atlas-slices`` each), when
         ``--atlas-dir`` exists;
       * on the bench cases (``--bench-dir``, when it exists): every slice of the acquired,
         motion-corrupted stacks is posed with :func:`svr.models.predict.predict_plane_poses` and
         compared with its true pose from ``truth_slices.json`` (``atlas.R``, ``atlas.t``: slice
         plane mm -> the source atlas's world frame; canonical = that frame shifted by the atlas
         mask centroid, checked against ``case.json``'s ``atlas_centre_mm``). The convention is
         verified first: the atlas cut at the true poses must reproduce the acquired slices
         (median CC >= 0.9), or the script stops. The bench cases are simulated from the atlas
         volumes GA24 and GA28 (held out by the model trained with ``--hold-out 24 28 32``).

       Per set: rotation and translation errors (median, mean), raw and up to the mirror twin,
       and slice CC
       (:func:`svr.models.evaluation.evaluate_poses`: the volume cut at the true and at the
       predicted pose), and the float16-vs-float32 prediction difference.
    3. ``OUT/README.md``: the model card (command, data, licence, size, the tables); the tables
       are also printed.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from bench_common import true_slice_poses

from svr.cli.common import resolve_device
from svr.files import atomic_write_text
from svr.geometry import se3_to_vector
from svr.image import load_nifti
from svr.image_metrics import ncc
from svr.metrics import pose_errors
from svr.models.checkpoint import CHECKPOINT_CONFIG, CHECKPOINT_WEIGHTS, load_checkpoint
from svr.models.evaluation import EvalConfig, evaluate_poses, summarize
from svr.models.network import SlicePoseNet
from svr.models.predict import load_pose_model, predict_plane_poses
from svr.models.pretrained.export import export_model
from svr.sampling.phantom import gestational_age_config, make_phantom
from svr.sampling.poses import VALIDATION_BRAIN_FRACTION, draw_validation_poses
from svr.sampling.slicer import SliceConfig, sample_slices
from svr.sampling.volume import CanonicalVolume, canonicalize, load_canonical_volume

ROOT = Path(__file__).resolve().parents[1]
TRAINING_COMMAND = (
    "OMP_NUM_THREADS=1 .venv/bin/svr train --output-dir runs/sym-heldout "
    "--atlas-dir ../shared/data/atlas/sb-fidon2021 --hold-out 24 28 32 --loss se3 "
    "--symmetry auto --backbone resnet --width 16 --depth 4 --size 64 --spacing 2 "
    "--rotation uniform --thickness-range 1.5 4.5 --shift-mm 6 --scale-range 0.85 1.15 "
    "--augment --steps 32000 --batch-size 32 --checkpoint-every 1000 --keep-checkpoints 40 "
    "--warmup-steps 500 --seed 0 --quiet"
)
DATA = {
    "name": "sb-fidon2021",
    "description": (
        "Spatio-temporal 3D MRI atlas of the developing fetal brain with spina bifida aperta: "
        "T2-weighted super-resolution volumes (0.8 mm) with brain masks, one per gestational "
        "week 21-34 (GA21-25 not operated, GA25-34 operated)"
    ),
    "citation": (
        "Fidon L, Viola E, Mufti N, et al. A spatio-temporal atlas of the developing fetal brain "
        "with spina bifida aperta. Open Research Europe 1:123 (2021)"
    ),
    "source": "Zenodo record 5524312, https://doi.org/10.5281/zenodo.5524312",
    "licence": "CC0 1.0",
}
BENCH_CASES = ("sb28-moderate", "sb24-large")
MAX_LISTED = 4  # more volumes in a row are counted, not listed
TRUTH_CC_MIN = 0.9  # median CC of acquired slices vs the atlas cut at their true poses
EULER_BOX = "Euler box (±90°, ±40 mm)"
UNIFORM = "uniform SO(3) (±40 mm)"


@dataclass
class Result:
    """Per-slice metrics of one volume or case under one pose distribution."""

    group: str
    source: str
    metrics: dict[str, np.ndarray]
    notes: list[str] = field(default_factory=list)


def parse_args() -> tuple[argparse.Namespace, str]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--checkpoint", type=Path, required=True, help="checkpoint folder")
    parser.add_argument("--out", type=Path, required=True, help="model folder to write")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument(
        "--training-command", default=TRAINING_COMMAND, help="the command that trained it"
    )
    parser.add_argument(
        "--atlas-dir", type=Path, default=ROOT.parent / "shared/data/atlas/sb-fidon2021"
    )
    parser.add_argument("--bench-dir", type=Path, default=ROOT.parent / "shared/data/bench")
    parser.add_argument(
        "--phantom-ga", type=float, nargs="+", default=[22.0, 26.0, 30.0, 34.0], help="weeks"
    )
    parser.add_argument("--num-slices", type=int, default=200, help="slices per volume and set")
    parser.add_argument(
        "--atlas-slices", type=int, default=40, help="slices per atlas volume and set (0: skip)"
    )
    parser.add_argument("--thickness", type=float, default=3.0, help="slice thickness, mm")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--device", default="auto", help="auto (cuda if available), cpu, cuda")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    return args, resolve_device(args.device)


def provenance(checkpoint: Path, command: str, atlas_dir: Path) -> dict:
    """What the model card and config record about how the model was made."""
    training = load_checkpoint(checkpoint).config.get("training") or {}
    sources = [Path(s).parent.name for s in training.get("data_sources", [])]
    run = training.get("run", {})
    return {
        "training_command": command,
        "data": {**DATA, "volumes": sources, "num_volumes": len(sources)},
        "steps": training.get("step"),
        "planned_steps": training.get("steps"),
        "batch_size": run.get("data", {}).get("batch_size"),
        "seed": run.get("seed"),
        "held_out": held_out_note(sources, atlas_dir),
    }


def held_out_note(sources: list[str], atlas_dir: Path) -> str:
    """Which volumes of the atlas folder training left out, in words."""
    missing = [f.name for f in sorted(atlas_dir.glob("GA*")) if f.name not in sources]
    if not missing:
        return "none: every atlas volume was used for training"
    return f"{', '.join(missing)} (not used for training)"


def random_pose_results(
    model: SlicePoseNet,
    reference: SlicePoseNet,
    slice_config: SliceConfig,
    volumes: list[tuple[str, CanonicalVolume]],
    group: str,
    rotation: str,
    num_slices: int,
    seed: int,
) -> list[Result]:
    """Random-pose slices of each volume: metrics of ``model``, and its gap to ``reference``."""
    results = []
    for i, (name, volume) in enumerate(volumes):
        generator = torch.Generator().manual_seed(seed + 1000 * i + (rotation == "uniform"))
        poses = draw_validation_poses(
            volume, num_slices, slice_config, generator, rotation, VALIDATION_BRAIN_FRACTION
        )
        slices = sample_slices(volume.image, poses, slice_config).float()
        device = next(model.parameters()).device
        predicted = model.predict_poses(slices[:, None].to(device)).double()
        gap = pose_errors(predicted, reference.predict_poses(slices[:, None].to(device)).double())
        metrics = evaluate_poses(volume, poses, predicted, EvalConfig(slice_config), slices)
        metrics["fp16_rotation_deg"] = gap["rotation_deg"].cpu().numpy()
        metrics["fp16_translation_mm"] = gap["translation_mm"].cpu().numpy()
        results.append(Result(f"{group}, {rotation_label(rotation)}", name, metrics))
    return results


def rotation_label(rotation: str) -> str:
    return EULER_BOX if rotation == "euler" else UNIFORM


def bench_result(model: SlicePoseNet, case: Path, atlas_dir: Path, device: str) -> Result:
    """Every acquired slice of a bench case posed by the model and compared with the truth."""
    info = json.loads((case / "case.json").read_text(encoding="utf-8"))
    atlas = atlas_dir / info["source"].removeprefix("fetal_SB_atlas_")
    volume = load_canonical_volume(atlas / "srr.nii.gz", atlas / "mask.nii.gz")
    if "atlas_centre_mm" in info:
        given = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
        if not torch.allclose(given, volume.centre_mm, atol=1e-3, rtol=0):
            raise SystemExit(
                f"{case}: atlas_centre_mm {given.tolist()} is not the mask centroid "
                f"{volume.centre_mm.tolist()} of {atlas}; the canonical frames differ"
            )
    thickness = float(np.mean(info["thickness"]))
    truth_json = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))
    true_poses, predicted, truth_cc = [], [], []
    for stack_info in truth_json["stacks"]:
        path = case / stack_info["file"]
        stack = load_nifti(path)
        mask = load_nifti(case / "masks" / path.name.replace(".nii", "_mask.nii"))
        truth = true_slice_poses(stack_info["slices"], "atlas", volume.centre_mm)
        if len(truth) != stack.shape[2]:
            raise SystemExit(f"{path}: {stack.shape[2]} slices but {len(truth)} true poses")
        spacing = torch.linalg.norm(stack.affine[:3, :2].double(), dim=0)
        if not torch.allclose(spacing[0], spacing[1], rtol=1e-4):
            raise SystemExit(f"{path}: in-plane spacing {spacing.tolist()} is not isotropic")
        # The convention check: the atlas cut at the true poses reproduces the acquired slices.
        acquired_grid = SliceConfig(stack.shape[:2], float(spacing[0]), thickness_mm=thickness)
        cut = sample_slices(volume.image, truth, acquired_grid).float()
        brain = (mask.data > 0.5).sum(dim=(0, 1)) > 0
        cc = ncc(stack.data.permute(2, 0, 1).float()[brain], cut[brain])
        truth_cc.append(cc.cpu().numpy())
        posed = predict_plane_poses(model, stack.to(device), mask.to(device), name=path.name)
        posed = posed.table(path.name)
        true_poses.append(truth[posed.slice_indices])
        predicted.append(posed.poses)
    truth_cc_all = np.concatenate(truth_cc)
    if np.median(truth_cc_all) < TRUTH_CC_MIN:
        raise SystemExit(
            f"{case}: the atlas cut at the true poses does not reproduce the acquired slices "
            f"(median CC {np.median(truth_cc_all):.3f} < {TRUTH_CC_MIN}); check the frames"
        )
    config = model.config
    eval_config = EvalConfig(SliceConfig(config.input_size, config.spacing_mm, thickness))
    metrics = evaluate_poses(
        volume.to(device),
        se3_to_vector(torch.cat(true_poses)),
        torch.cat(predicted),
        eval_config,
    )
    note = (
        f"{case.name}: acquired slices vs the atlas cut at their true poses, median CC "
        f"{np.median(truth_cc_all):.3f} over {len(truth_cc_all)} slices (convention check; "
        f"source atlas {atlas.name}, {thickness:g} mm slices)"
    )
    return Result("bench stacks (motion-corrupted)", case.name, metrics, [note])


def stat(metrics: dict[str, np.ndarray], key: str, fmt: str) -> str:
    s = summarize({key: metrics[key]})[key]
    return f"{s['median']:{fmt}} / {s['mean']:{fmt}}"


def table(results: list[Result], by: str) -> str:
    """Markdown table: one row per group (``by="group"``) or per volume (``by="source"``)."""
    rows: dict[tuple[str, str], list[Result]] = {}
    for r in results:
        key = (r.group, "all" if by == "group" else r.source)
        rows.setdefault(key, []).append(r)
    lines = [
        "| set | volume | slices | rotation error (°) median / mean "
        "| translation error (mm) median / mean | rotation up to the mirror twin (°) median / "
        "mean | translation up to the twin (mm) median / mean | CC median / mean |",
        "|---|---|---:|---:|---:|---:|---:|---:|",
    ]
    for (group, source), members in rows.items():
        merged = {k: np.concatenate([m.metrics[k] for m in members]) for k in members[0].metrics}
        names = [m.source for m in members]
        label = source if by == "source" else ", ".join(names)
        if len(names) > MAX_LISTED:
            label = f"{len(names)} volumes"
        lines.append(
            f"| {group} | {label} | {len(merged['cc'])} | {stat(merged, 'rotation_deg', '.1f')} "
            f"| {stat(merged, 'translation_mm', '.1f')} "
            f"| {stat(merged, 'rotation_twin_deg', '.1f')} "
            f"| {stat(merged, 'translation_twin_mm', '.1f')} | {stat(merged, 'cc', '.3f')} |"
        )
    return "\n".join(lines)


def fp16_gap(results: list[Result]) -> str:
    gaps = [r for r in results if "fp16_rotation_deg" in r.metrics]
    if not gaps:
        return "not measured"
    rot = np.concatenate([r.metrics["fp16_rotation_deg"] for r in gaps])
    trans = np.concatenate([r.metrics["fp16_translation_mm"] for r in gaps])
    return (
        f"largest difference between the float16 and float32 predictions over {len(rot)} "
        f"slices: {rot.max():.3g}° and {trans.max():.3g} mm"
    )


def model_card(
    out: Path,
    config: dict,
    params: int,
    results: list[Result],
    args: argparse.Namespace,
    device: str,
) -> str:
    prov, model = config["provenance"], config["model"]
    weights = out / CHECKPOINT_WEIGHTS
    size = sum((out / f).stat().st_size for f in (CHECKPOINT_WEIGHTS, CHECKPOINT_CONFIG))
    data = prov["data"]
    backbone = model["backbone"]
    step_note = (
        ""
        if prov["steps"] == prov["planned_steps"]
        else f" **(intermediate checkpoint: step {prov['steps']} of {prov['planned_steps']})**"
    )
    notes = [n for r in results for n in r.notes]
    sections = [
        "# Default slice-pose model (`--model default`)",
        "A CNN that predicts the pose of a 2D fetal-brain MRI slice in canonical (atlas) space, "
        "trained with the SE(3) geodesic loss. Load it with `svr predict --model default ...`, "
        "`svr evaluate --checkpoints default ...` or "
        '`svr.models.predict.load_pose_model("default")` '
        "(safetensors + JSON: loading runs no code; the float16 weights are cast back to "
        "float32).",
        "## Model",
        f"- {backbone['name']} backbone, width {backbone['width']}, depth {backbone['depth']}, "
        f"{params:,} weights; output `{model['representation']}` (rotation vector, rad, and "
        f"translation, mm, of the slice centre in the canonical frame"
        f"{'; regressed as 6D rotation columns' if model.get('se3_rotation') == '6d' else ''})."
        f"\n- Trained up to the mirror twin about "
        f"{symmetry_words(model.get('symmetry_planes', []))}: a prediction stands for the pose or "
        "its mirror twin, and a stack's slice order decides which "
        "(`svr.reconstruction.initialisation.slice_model.disambiguate_stack`).\n"
        f"- Input: {model['input_size'][0]}×{model['input_size'][1]} slices at "
        f"{model['spacing_mm']:g} mm, masked, divided by the in-mask 99th percentile "
        f"(`svr.models.predict` prepares stacks this way).\n"
        f"- Files: `{CHECKPOINT_WEIGHTS}` (float16, {weights.stat().st_size / 1e6:.2f} MB) and "
        f"`{CHECKPOINT_CONFIG}`; {size / 1e6:.2f} MB in all.\n"
        f"- Trained for {prov['steps']} steps of {prov['batch_size']} slices{step_note}, "
        f"seed {prov['seed']}.",
        "## Training command",
        f"```bash\n{prov['training_command']}\n```",
        "## Training data and licence",
        f"{data['num_volumes']} volumes of the {data['name']} atlas ({', '.join(data['volumes'])})"
        f": {data['description']}. {data['citation']}. {data['source']}. Licence: "
        f"{data['licence']}. Held out: {prov['held_out']}. The held-out ages and the procedural "
        "phantoms are anatomy the model did not see; the bench cases are simulated from GA24 "
        "and GA28 of the atlas.",
        "## Evaluation",
        f"Random-pose slices: {args.num_slices} per phantom and held-out atlas volume and "
        f"{args.atlas_slices} per training atlas volume, per pose set, {args.thickness:g} mm "
        "thick (Gaussian PSF), "
        f"{model['input_size'][0]}×{model['input_size'][1]} at {model['spacing_mm']:g} mm, "
        f"kept when ≥ {VALIDATION_BRAIN_FRACTION:.0%} of the pixels are brain, seed {args.seed}. "
        "Bench stacks: every slice with a nonempty mask, posed with "
        "`svr.models.predict.predict_plane_poses`. Rotation error: geodesic angle; translation "
        "error: distance between the slice centres; CC: the volume cut at the true vs the "
        "predicted pose (`svr.models.evaluation.evaluate_poses`). The phantom is procedural "
        "(`svr.sampling.phantom`) and looks unlike real anatomy in its details, so its rows are a "
        "hard out-of-distribution test.",
        table(results, "group"),
        "By volume:",
        table([r for r in results if not r.group.startswith("atlas (seen")], "source"),
        "Checks: " + "; ".join([*notes, fp16_gap(results)]) + ".",
        f"Evaluated on {device} with fetal-svr {config['export']['versions']['fetal_svr']}, "
        f"torch {torch.__version__}, Python {platform.python_version()}, by "
        f"`benchmarks/export_default_model.py`.",
    ]
    return "\n\n".join(sections) + "\n"


def symmetry_words(planes: list[dict]) -> str:
    if not planes:
        return "no plane (plain loss)"
    return "; ".join(
        f"the plane with normal ({', '.join(f'{v:.3f}' for v in p['normal'])}) at "
        f"{p['offset_mm']:.2f} mm"
        for p in planes
    )


def main() -> int:
    args, device = parse_args()
    prov = provenance(args.checkpoint, args.training_command, args.atlas_dir)
    if prov["steps"] != prov["planned_steps"]:
        print(
            f"warning: {args.checkpoint} is step {prov['steps']} of {prov['planned_steps']}",
            file=sys.stderr,
        )
    out = export_model(args.checkpoint, args.out, provenance=prov, overwrite=args.overwrite)
    print(f"exported {args.checkpoint} -> {out}")
    model = load_pose_model(out, device)
    config = model.config
    reference = load_pose_model(args.checkpoint, device)
    slice_config = SliceConfig(config.input_size, config.spacing_mm, thickness_mm=args.thickness)

    phantoms = [
        (
            f"phantom GA {ga:g}",
            canonicalize(*make_phantom(gestational_age_config(ga)), name="phantom").to(device),
        )
        for ga in args.phantom_ga
    ]
    results = []
    for rotation in ("euler", "uniform"):
        results += random_pose_results(
            model,
            reference,
            slice_config,
            phantoms,
            "phantom",
            rotation,
            args.num_slices,
            args.seed,
        )
    if args.atlas_slices > 0 and args.atlas_dir.is_dir():
        atlas = [
            (folder.name, load_canonical_volume(folder / "srr.nii.gz", folder / "mask.nii.gz"))
            for folder in sorted(args.atlas_dir.glob("GA*"))
        ]
        atlas = [(name, volume.to(device)) for name, volume in atlas]
        seen = set(prov["data"]["volumes"])
        for rotation in ("euler", "uniform"):
            for label, members in (
                ("atlas held out", [a for a in atlas if a[0] not in seen]),
                ("atlas (seen in training)", [a for a in atlas if a[0] in seen]),
            ):
                if members:
                    results += random_pose_results(
                        model,
                        reference,
                        slice_config,
                        members,
                        label,
                        rotation,
                        args.num_slices if label == "atlas held out" else args.atlas_slices,
                        args.seed,
                    )
    for name in BENCH_CASES:
        case = args.bench_dir / name
        if case.is_dir() and args.atlas_dir.is_dir():
            results.append(bench_result(model, case, args.atlas_dir, device))
        else:
            print(f"skipping bench case {case} (not found, or no --atlas-dir)", file=sys.stderr)

    exported = json.loads((out / CHECKPOINT_CONFIG).read_text(encoding="utf-8"))
    params = sum(p.numel() for p in model.parameters())
    card = model_card(out, exported, params, results, args, device)
    atomic_write_text(out / "README.md", card)
    print(table(results, "group"))
    print()
    print(table([r for r in results if not r.group.startswith("atlas (seen")], "source"))
    print(f"\n{fp16_gap(results)}\nwrote {out / 'README.md'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
