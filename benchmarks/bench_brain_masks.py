r"""Automatic brain masks against manual ones, and reconstruction with them (issue 14).

Part ``masks``: the brain-mask model (``--mask-model``, default the shipped one) segments every
stack of

* the real clinical scan ``stacks/real-mialsrtk-sub01`` (6 whole-uterus stacks, manual masks);
* ``stacks/sim-fabian`` (4 cropped stacks of 3 simulated subjects, their masks);
* ``stacks/sim-svrtk-phantom`` (6 cropped stacks; the one mask, drawn on stack 2, is resampled
  onto each stack by world position, nearest neighbour, as ``svr reconstruct`` resamples masks);
* the bench cases ``bench/sb28-moderate`` and ``bench/sb24-large`` (their masks),

and reports per stack Dice, recall (the fraction of the manual brain inside ours) and precision
against the given masks, the wall time of :func:`svr.masking.segment_stack` with
``--threads`` torch threads, and the peak resident memory of a fresh process that loads the model
and segments the first real stack in which a brain was found (``VmHWM``, with the same
process's peak before the call).
The reference method is the toolkit's former automatic mask, Otsu (``--auto-masks otsu``), on
the same stacks (ratio columns).

Part ``masks`` also fuses the automatic masks of each dataset whose stacks are of one fetus
(the real scan, the phantom, the bench cases; not FaBiAN, whose 4 stacks are of 3 subjects) across
its stacks, as ``svr segment-stack --fuse-masks`` does
(:func:`svr.masking.fuse.fuse_stack_masks`, thickness = slice spacing, each stack
voting with the network's probabilities), and scores the fused masks in the same way; the
fusion's wall time is given per stack. A second table compares that fusion with one whose
stacks vote with their binary masks (the fusion of the previous release).

Part ``recon``: ``svr reconstruct``'s pipeline (default settings, ``--registration stack``) on
the real scan's stacks in which the model finds a brain, once with the manual masks, once
with the automatic ones and once with the automatic ones fused across stacks; slice consistency
is the mean over slices of the NCC of each observed slice with its simulation from the volume
(the transforms table's ``ncc`` column). QA figures show the reconstructions and the automatic
masks.

Part ``simval`` (not in ``all``): held-out *simulated* whole-uterus stacks, to choose between
models without the real scan: ``--sim-cases`` scenes (``make_scene`` with the tiled recipe's
localiser settings, masks up to the skull; scene seeds 5000 and up, while training draws its
scene seeds at random from [0, 2**31), so a shared scene is improbable), each cut into 2 stacks
(``--sim-stacks``) of 3.3 mm slices of 1.125 mm pixels (as the clinical scan) with moderate
motion, noise, bias field and signal voids; every model of ``--sim-models`` (comma-separated)
segments the same stacks, and with 3 or more stacks per scene its masks of each scene are also
fused (``MODEL, fused`` rows; ``MODEL, fused (mask votes)`` with binary votes).
``--sim-faces`` gives the heads faces, ``--sim-spinal-cord`` ends them at the skull base and
``--sim-mask-fraction`` cuts the true masks with the slices' profiles
(``SimulationConfig.mask_fraction``; ``--sim-grazing-ratio`` only on the slices grazing the
head's ends): the conventions of models trained with ``--faces --spinal-cord
--partial-volume-masks [--grazing-only]``. The brains are the atlas's, as in training:
this measures the scenes and acquisitions held out, not unseen anatomy.

Part ``consistency`` (not in ``all``): how well the manual masks of the real scan agree with
each other: each stack's manual mask against the vote of the other five stacks' manual masks on
its planes (:func:`svr.masking.fuse.leave_one_out_votes` above 0.5, with the slice
poses of a reconstruction with the manual masks, excluded slices left out), beside the automatic
masks' Dice and recall, own and fused; then both votes at lower thresholds (what recall a mask
consistent in 3D reaches, and at what Dice); then the SVRTK phantom's one mask against each
stack's head (the Dice of the two and the distance between their centroids).

Part ``opening`` (not in ``all``): the clean-up's opening (``BrainMaskConfig.opening_mm`` and
``regrow_mm``) swept over settings on every stack of part ``masks`` and of part ``simval``: the
``--mask-model`` probabilities of each stack are computed once and cleaned up with each setting
(:func:`svr.masking.clean_up_mask`); Dice min / mean per dataset.

Run from the repository root on 2 quiet cores::

    python benchmarks/bench_brain_masks.py --threads 2 \\
        --results benchmarks/results/brain-masks.md
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

from svr.image import Image, load_nifti, mask_on_grid
from svr.masking import BrainNotFoundError, load_brain_masker, segment_stack

MASK_SUFFIX = "T2w_desc-brain_mask.nii.gz"
DATA = Path(__file__).resolve().parents[1] / ".." / "shared" / "data"


def datasets(data: Path) -> dict[str, list[tuple[Path, Path]]]:
    """Dataset name -> (stack, mask) files."""
    real = data / "stacks" / "real-mialsrtk-sub01"
    fabian = data / "stacks" / "sim-fabian"
    phantom = data / "stacks" / "sim-svrtk-phantom"
    out = {
        "real-mialsrtk-sub01": [
            (
                real / f"sub-01_run-{n}_T2w.nii.gz",
                real / f"sub-01_run-{n}_T2w_desc-brain_mask.nii.gz",
            )
            for n in range(1, 7)
        ],
        "sim-fabian": [
            (fabian / f"{s}_T2w.nii.gz", fabian / f"{m}_mask.nii.gz")
            for s, m in (
                ("sub-simu005_ses-01_run-2", "sub-simu005_ses-01_run-2"),
                ("sub-simu005_ses-01_run-6", "sub-simu005_ses-01_run-6"),
                ("sub-simu009_ses-01_run-7", "sub-simu009_run-7"),
                ("sub-simu038_ses-01_run-2", "sub-simu038_ses-01_run-2"),
            )
        ],
        "sim-svrtk-phantom": [
            (phantom / f"simulated-stack-d{n}.nii.gz", phantom / "mask-for-stack-2.nii.gz")
            for n in range(6)
        ],
    }
    for case in ("sb28-moderate", "sb24-large"):
        folder = data / "bench" / case
        out[case] = [
            (stack, folder / "masks" / f"{stack.name[: -len('.nii.gz')]}_mask.nii.gz")
            for stack in sorted((folder / "stacks").glob("stack*.nii.gz"))
        ]
    return out


def scores(ours: torch.Tensor, truth: torch.Tensor) -> dict[str, float]:
    overlap = float((ours & truth).sum())
    return {
        "dice": 2 * overlap / max(float(ours.sum() + truth.sum()), 1.0),
        "recall": overlap / max(float(truth.sum()), 1.0),
        "precision": overlap / max(float(ours.sum()), 1.0),
    }


def otsu_masks(stacks: list[Image], names: list[str]) -> list[torch.Tensor]:
    """The former automatic masks (``MaskingConfig(method="otsu")``), on each stack's grid."""
    from svr.masking.otsu import otsu_mask

    out = []
    for n, (image, name) in enumerate(zip(stacks, names, strict=True)):
        try:
            out.append(otsu_mask(image, stacks[:n] + stacks[n + 1 :], name))
        except ValueError:
            out.append(torch.zeros(image.shape, dtype=torch.bool))
    return out


# The peak is VmHWM (kB) of /proc/self/status: ru_maxrss keeps the parent's high-water mark
# across fork and exec on Linux, so in a child of this benchmark it reported the benchmark's own
# peak (figures before 2026-11-24's third session were inflated by it).
PEAK_SCRIPT = """
import sys, time, torch
def peak_kb():
    with open("/proc/self/status") as status:
        return next(float(line.split()[1]) for line in status if line.startswith("VmHWM:"))
torch.set_num_threads(int(sys.argv[2]))
from svr.image import load_nifti
from svr.masking import load_brain_masker, segment_stack
masker = load_brain_masker(sys.argv[3])
stack = load_nifti(sys.argv[1])
before = peak_kb()
try:
    segment_stack(stack, masker)
except ValueError:  # no brain found: the work up to that point is measured
    pass
print(before / 1024, peak_kb() / 1024)
"""


# Datasets whose stacks are of one fetus (at least 3): their masks are also fused across stacks.
ONE_FETUS = ("real-mialsrtk-sub01", "sim-svrtk-phantom", "sb28-moderate", "sb24-large")


def part_masks(args: argparse.Namespace, report: dict) -> list[str]:
    from svr.masking.fuse import fuse_stack_masks

    masker = load_brain_masker(args.mask_model)
    lines = [
        "| dataset | stack | shape | Dice | recall | precision | Otsu Dice | "
        "Dice ratio (ours / Otsu) | time (s) | fused: Dice | recall | precision |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    rows = []
    fusion_seconds = {}
    for dataset, pairs in datasets(args.data).items():
        stacks = [load_nifti(s) for s, _ in pairs]
        names = [str(s) for s, _ in pairs]
        otsu = otsu_masks(stacks, names)
        found, part = [], []
        for (stack_path, mask_path), stack, otsu_mask in zip(pairs, stacks, otsu, strict=True):
            truth = mask_on_grid(load_nifti(mask_path), stack)
            began = time.perf_counter()
            try:
                result = segment_stack(stack, masker, name=stack_path.name)
                mask, probability, error = result.mask, result.probability, ""
            except BrainNotFoundError as err:
                mask, error = torch.zeros(stack.shape, dtype=torch.bool), str(err)
                probability = torch.zeros(stack.shape)
            seconds = time.perf_counter() - began
            ours, ref = scores(mask, truth), scores(otsu_mask, truth)
            part.append(
                {
                    "dataset": dataset,
                    "stack": stack_path.name,
                    "shape": list(stack.shape),
                    **ours,
                    "otsu_dice": ref["dice"],
                    "seconds": seconds,
                    "error": error,
                }
            )
            found.append((stack, mask, truth, not error, probability))
        if dataset in ONE_FETUS and sum(f[3] for f in found) >= 3:
            kept = [f for f in found if f[3]]
            widths = [float(f[0].spacing[2]) for f in kept]  # thickness: the slice spacing
            stacks_kept, masks_kept = [f[0] for f in kept], [f[1] for f in kept]
            began = time.perf_counter()
            fused = fuse_stack_masks(
                stacks_kept, masks_kept, widths, probabilities=[f[4] for f in kept]
            )
            fusion_seconds[dataset] = time.perf_counter() - began
            hard = fuse_stack_masks(stacks_kept, masks_kept, widths)  # votes of the masks
            fused_masks, hard_masks = iter(fused.masks), iter(hard.masks)
            for row, (_, _, truth, ok, _) in zip(part, found, strict=True):
                if ok:
                    row["fused"] = scores(next(fused_masks), truth)
                    row["fused_mask_votes"] = scores(next(hard_masks), truth)
        for row in part:
            ratio = row["dice"] / row["otsu_dice"] if row["otsu_dice"] > 0 else float("inf")
            fused_cells = (
                f"{row['fused']['dice']:.3f} | {row['fused']['recall']:.3f} | "
                f"{row['fused']['precision']:.3f}"
                if "fused" in row
                else "- | - | -"
            )
            lines.append(
                f"| {dataset} | {row['stack']} | {'x'.join(map(str, row['shape']))} | "
                f"{row['dice']:.3f} | {row['recall']:.3f} | {row['precision']:.3f} | "
                f"{row['otsu_dice']:.3f} | {ratio:.2f} | {row['seconds']:.2f} | {fused_cells} |"
            )
            print(lines[-1], flush=True)
        rows += part
    report["stacks"] = rows
    report["fusion_seconds"] = fusion_seconds
    summary = [
        "",
        "| dataset | min Dice | mean Dice | min recall | mean time (s) | fused: min Dice | "
        "mean Dice | min recall | mean recall | min Dice ratio (fused / own) | fusion time "
        "per stack (s) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for dataset in dict.fromkeys(r["dataset"] for r in rows):
        part = [r for r in rows if r["dataset"] == dataset]
        cells = "- | - | - | - | - | -"
        with_fused = [r for r in part if "fused" in r]
        if with_fused:
            fused_dice = [r["fused"]["dice"] for r in with_fused]
            fused_recall = [r["fused"]["recall"] for r in with_fused]
            ratio = min(fused_dice) / min(r["dice"] for r in with_fused)
            cells = (
                f"{min(fused_dice):.3f} | {np.mean(fused_dice):.3f} | {min(fused_recall):.3f} | "
                f"{np.mean(fused_recall):.3f} | {ratio:.3f} | "
                f"{fusion_seconds[dataset] / len(with_fused):.2f}"
            )
        summary.append(
            f"| {dataset} | {min(r['dice'] for r in part):.3f} | "
            f"{np.mean([r['dice'] for r in part]):.3f} | {min(r['recall'] for r in part):.3f} | "
            f"{np.mean([r['seconds'] for r in part]):.2f} | {cells} |"
        )
    summary += [
        "",
        "Fusion with soft votes (each stack votes with its network probability, as `svr` fuses) "
        "against votes of the masks (0 / 1):",
        "",
        "| dataset | soft votes: Dice min / mean | recall min / mean | mask votes: Dice min / "
        "mean | recall min / mean | min Dice ratio (soft / mask votes) |",
        "|---|---|---|---|---|---|",
    ]
    for dataset in dict.fromkeys(r["dataset"] for r in rows if "fused" in r):
        part = [r for r in rows if r["dataset"] == dataset and "fused" in r]
        cells = []
        for key in ("fused", "fused_mask_votes"):
            dice = [r[key]["dice"] for r in part]
            recall = [r[key]["recall"] for r in part]
            cells.append(
                f"{min(dice):.3f} / {np.mean(dice):.3f} | {min(recall):.3f} / {np.mean(recall):.3f}"
            )
        ratio = min(r["fused"]["dice"] for r in part) / min(
            r["fused_mask_votes"]["dice"] for r in part
        )
        summary.append(f"| {dataset} | {cells[0]} | {cells[1]} | {ratio:.3f} |")
    real = [r for r in rows if r["dataset"] == "real-mialsrtk-sub01"]
    segmented = [r["stack"] for r in real if not r["error"]] or [real[0]["stack"]]
    first = args.data / "stacks" / "real-mialsrtk-sub01" / segmented[0]
    out = subprocess.run(
        [sys.executable, "-c", PEAK_SCRIPT, str(first), str(args.threads), args.mask_model],
        capture_output=True,
        text=True,
        check=True,
    ).stdout.split()
    before, after = float(out[0]), float(out[1])
    report["peak_rss_mib"] = {"before_segmenting": before, "after_segmenting": after}
    summary.append("")
    summary.append(
        f"Peak resident memory of a fresh process segmenting {first.name} (320x320x22) with "
        f"{args.threads} threads: {after:.0f} MiB (the same process's peak before the call, "
        f"after loading torch, the model and the stack: {before:.0f} MiB)."
    )
    print("\n".join(summary))
    return lines + summary


def part_recon(args: argparse.Namespace, report: dict) -> list[str]:
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.pipeline import reconstruct
    from svr.reconstruction.qa import masks_figure, qa_figure
    from svr.reconstruction.stacks import prepare_stacks

    pairs = datasets(args.data)["real-mialsrtk-sub01"]
    masker = load_brain_masker(args.mask_model)
    images = [load_nifti(s) for s, _ in pairs]
    found, failed = [], []
    for (stack_path, mask_path), image in zip(pairs, images, strict=True):
        try:
            result = segment_stack(image, masker, name=stack_path.name)
            found.append((stack_path, mask_path, image, result.mask, result.probability))
        except BrainNotFoundError as err:
            failed.append(str(err))
    report["recon_not_found"] = failed
    lines = ["", f"Stacks where no brain was found (left out of both runs): {len(failed)}"]
    lines += [f"- {message}" for message in failed]
    if args.figures is not None and found:
        masks_figure(
            [(str(p), image, auto) for p, _, image, auto, _ in found],
            args.figures / "real-scan-automatic-masks.png",
            overwrite=True,
            title="svr segment-stack on real-mialsrtk-sub01 (stacks where a brain was found)",
        )
    if len(found) < 2:
        lines.append("Fewer than 2 stacks with an automatic mask: no reconstruction compared.")
        return lines
    config = ReconstructionConfig.preset("stack")
    names = [str(p) for p, *_ in found]
    results = {}
    mask_sets = [
        ("manual", [load_nifti(m) for _, m, *_ in found]),
        ("automatic", [Image(auto.float(), image.affine) for _, _, image, auto, _ in found]),
    ]
    if len(found) >= 3:
        from svr.masking.fuse import fuse_stack_masks

        fused = fuse_stack_masks(
            [f[2] for f in found],
            [f[3] for f in found],
            3.0,
            names,
            probabilities=[f[4] for f in found],
        )
        mask_sets.append(
            (
                "automatic, fused",
                [Image(m.float(), f[2].affine) for m, f in zip(fused.masks, found, strict=True)],
            )
        )
    per_slice: dict[str, dict[tuple[int, int], float]] = {}
    for name, masks in mask_sets:
        began = time.perf_counter()
        stacks = prepare_stacks([f[2] for f in found], masks, 3.0, names=names)
        result = reconstruct(stacks, config)
        seconds = time.perf_counter() - began
        ncc = result.slice_ncc.double()
        ids, planes = result.slices.stack_ids.tolist(), result.slices.slice_indices.tolist()
        keys = zip(ids, planes, strict=True)
        per_slice[name] = dict(zip(keys, ncc.tolist(), strict=True))
        common = per_slice["manual"].keys() & per_slice[name].keys()
        results[name] = {
            "mean_ncc": float(ncc.mean()),
            "mean_ncc_kept": float(ncc[~result.excluded].mean()),
            "mean_ncc_manual_slices": float(np.mean([per_slice[name][k] for k in common])),
            "manual_slices_present": len(common),
            "slices": len(ncc),
            "excluded": int(result.excluded.sum()),
            "seconds": seconds,
        }
        if args.figures is not None:
            path = args.figures / f"real-scan-{name.replace(', ', '-')}-masks-qa.png"
            qa_figure(result, path, overwrite=True, notes=[f"masks: {name}"])
        print(name, results[name], flush=True)
    report["recon"] = results
    manual, auto = results["manual"], results["automatic"]
    fused_line = []
    if "automatic, fused" in results:
        fused = results["automatic, fused"]
        difference = fused["mean_ncc"] - manual["mean_ncc"]
        same = fused["mean_ncc_manual_slices"] - manual["mean_ncc"]
        fused_line = [
            f"Fused automatic masks minus manual: {difference:+.4f} (all slices), {same:+.4f} "
            "(on the manual run's slices)."
        ]
    return [
        *lines,
        "",
        f"`svr reconstruct` (stack registration, default settings, thickness 3 mm) on the "
        f"{len(found)} stacks with an automatic mask ({', '.join(p.name for p, *_ in found)}):",
        "",
        "The last NCC column is the mean over the slices that the manual masks' run has (those",
        "of them that the run has too): a mask that takes in more of the head's thin end slices,",
        "whose NCC is low, lowers the mean over all slices without fitting any slice worse.",
        "",
        "| masks | slices | excluded | mean NCC (all slices) | mean NCC (kept) | mean NCC "
        "(the manual run's slices) | time (s) |",
        "|---|---|---|---|---|---|---|",
        *(
            f"| {k} | {v['slices']} | {v['excluded']} | {v['mean_ncc']:.4f} | "
            f"{v['mean_ncc_kept']:.4f} | {v['mean_ncc_manual_slices']:.4f} "
            f"({v['manual_slices_present']}) | {v['seconds']:.1f} |"
            for k, v in results.items()
        ),
        "",
        f"Slice consistency, automatic minus manual: {auto['mean_ncc'] - manual['mean_ncc']:+.4f} "
        f"(all slices), {auto['mean_ncc_manual_slices'] - manual['mean_ncc']:+.4f} (on the "
        "manual run's slices) (target: within 0.01).",
        *fused_line,
    ]


def part_consistency(args: argparse.Namespace, report: dict) -> list[str]:
    """How well the other stacks' manual masks predict each stack's (the masks' own agreement)."""
    from svr.masking.fuse import fuse_stack_masks, leave_one_out_votes
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.pipeline import reconstruct
    from svr.reconstruction.stacks import prepare_stacks

    pairs = datasets(args.data)["real-mialsrtk-sub01"]
    images = [load_nifti(s) for s, _ in pairs]
    manual = [
        mask_on_grid(load_nifti(m), image) for (_, m), image in zip(pairs, images, strict=True)
    ]
    names = [p.name for p, _ in pairs]
    stacks = prepare_stacks(images, [load_nifti(m) for _, m in pairs], 3.0, names=names)
    result = reconstruct(stacks, ReconstructionConfig.preset("stack"), progress=False)
    kept = result.slices.subset(~result.excluded)
    votes = leave_one_out_votes(images, manual, kept, [3.0] * len(images))
    masker = load_brain_masker(args.mask_model)
    results = [segment_stack(image, masker, name=n) for image, n in zip(images, names, strict=True)]
    own = [result.mask for result in results]
    fusion = fuse_stack_masks(
        images, own, 3.0, names, probabilities=[result.probability for result in results]
    )
    fused = fusion.masks
    lines = [
        "",
        "Manual masks of the real scan against the vote of the other 5 stacks' manual masks",
        "(`leave_one_out_votes` > 0.5, slice poses of a reconstruction with the manual masks), and",
        "the automatic masks (own, fused) against the manual ones:",
        "",
        "| stack | manual vs the others' manual: Dice | recall | automatic vs manual: Dice | "
        "recall | fused vs manual: Dice | recall |",
        "|---|---|---|---|---|---|---|",
    ]
    rows = []
    for name, vote, truth, mine, joint in zip(names, votes, manual, own, fused, strict=True):
        row = {
            "stack": name,
            "manual_vs_others": scores(vote > 0.5, truth),
            "automatic": scores(mine, truth),
            "fused": scores(joint, truth),
        }
        rows.append(row)
        cells = " | ".join(
            f"{row[key]['dice']:.3f} | {row[key]['recall']:.3f}"
            for key in ("manual_vs_others", "automatic", "fused")
        )
        lines.append(f"| {name} | {cells} |")
        print(lines[-1], flush=True)
    report["consistency"] = rows
    lines += [
        "",
        "Both votes thresholded lower (the masks they make, not cleaned up): the others' manual",
        "masks (leave one out) and all stacks' automatic soft votes (`FusedMasks.votes`), each",
        "against the manual masks, Dice and recall min / mean over the 6 stacks. A 3D-consistent",
        "mask drawn as the manual masks are reaches recall 0.97 at the threshold where its Dice",
        "is still this high:",
        "",
        "| threshold | manual (leave one out): Dice | recall | automatic (fused vote): Dice | "
        "recall |",
        "|---|---|---|---|---|",
    ]
    report["consistency_thresholds"] = {}
    for threshold in (0.5, 0.4, 0.3, 0.2, 0.1):
        cells = []
        for key, levels in (("manual", votes), ("automatic", fusion.votes)):
            got = [scores(v > threshold, t) for v, t in zip(levels, manual, strict=True)]
            report["consistency_thresholds"][f"{key} {threshold:g}"] = got
            dice, recall = [g["dice"] for g in got], [g["recall"] for g in got]
            cells.append(
                f"{min(dice):.3f} / {np.mean(dice):.3f} | {min(recall):.3f} / {np.mean(recall):.3f}"
            )
        lines.append(f"| {threshold:g} | {' | '.join(cells)} |")
        print(lines[-1], flush=True)
    lines += phantom_reference(args, report)
    return lines


HEAD_LEVELS = (0.02, 0.05, 0.1, 0.2, 0.3, 0.4)
"""Fractions of a stack's 99th percentile above which :func:`phantom_reference` calls it head."""
HEAD_GROWTH_MM = (-3, -2, -1, 0, 1, 2, 3, 4, 5)
"""Distances (mm) by which :func:`phantom_reference` grows (> 0) or shrinks (< 0) a head."""


def phantom_reference(args: argparse.Namespace, report: dict) -> list[str]:
    """How well the SVRTK phantom's one mask (drawn on stack 2) fits each stack's head.

    The head is what the stack shows: its voxels above 5 % of the 99th percentile, holes
    filled. Its Dice with the resampled mask is what a mask of the whole visible head scores,
    and the distance between their centroids shows the motion between the stacks that the
    mask, resampled through the headers, does not follow. The best Dice over heads at every
    level of :data:`HEAD_LEVELS`, each grown or shrunk by every distance of
    :data:`HEAD_GROWTH_MM` (54 masks, the best chosen against the reference itself), bounds what
    a mask that follows the stack's content can score against this reference.
    """
    from scipy import ndimage

    lines = [
        "",
        "The SVRTK phantom's mask (drawn on stack 2, resampled through the headers) against each",
        "stack's head (voxels above 5 % of the 99th percentile, holes filled), and the best Dice",
        f"of {len(HEAD_LEVELS) * len(HEAD_GROWTH_MM)} masks made from the head (levels "
        f"{', '.join(f'{100 * v:g}' for v in HEAD_LEVELS)} % of the 99th percentile, each grown or "
        f"shrunk by {', '.join(f'{v:+d}' for v in HEAD_GROWTH_MM)} mm), chosen against the",
        "reference: what a mask that follows the stack's content can reach at best:",
        "",
        "| stack | Dice (mask, head) | centroid distance (mm) | mask / head volume | best Dice "
        "of a head mask | its level, growth (mm) |",
        "|---|---|---|---|---|---|",
    ]
    rows = []
    for stack_path, mask_path in datasets(args.data)["sim-svrtk-phantom"]:
        stack = load_nifti(stack_path)
        mask = mask_on_grid(load_nifti(mask_path), stack).numpy()
        data = stack.data.numpy()
        top = np.percentile(data[data > 0], 99)
        head = ndimage.binary_fill_holes(data > 0.05 * top)
        spacing = stack.spacing.double().numpy()
        shift = (np.argwhere(mask).mean(0) - np.argwhere(head).mean(0)) * spacing
        best = (0.0, HEAD_LEVELS[0], 0)
        for level in HEAD_LEVELS:
            region = ndimage.binary_fill_holes(data > level * top)
            outside = ndimage.distance_transform_edt(~region, sampling=spacing)
            inside = ndimage.distance_transform_edt(region, sampling=spacing)
            for grow in HEAD_GROWTH_MM:
                candidate = outside <= grow if grow >= 0 else inside > -grow
                dice = scores(torch.from_numpy(candidate), torch.from_numpy(mask))["dice"]
                best = max(best, (dice, level, grow))
        row = {
            "stack": stack_path.name,
            "dice": scores(torch.from_numpy(head), torch.from_numpy(mask))["dice"],
            "centroid_mm": float(np.linalg.norm(shift)),
            "volume_ratio": float(mask.sum() / head.sum()),
            "best_head_dice": best[0],
            "best_head_level": best[1],
            "best_head_growth_mm": best[2],
        }
        rows.append(row)
        lines.append(
            f"| {row['stack']} | {row['dice']:.3f} | {row['centroid_mm']:.1f} | "
            f"{row['volume_ratio']:.2f} | {best[0]:.3f} | {100 * best[1]:g} %, {best[2]:+d} |"
        )
        print(lines[-1], flush=True)
    report["phantom_reference"] = rows
    return lines


def simval_stacks(args: argparse.Namespace) -> list[tuple[str, Image, torch.Tensor]]:
    """The held-out simulated stacks of part ``simval``: (case name, stack, bool brain mask)."""
    import dataclasses

    from svr.masking.train import stage_data
    from svr.sampling.scenes import make_scene
    from svr.sampling.simulate import SimulationConfig, simulate_case
    from svr.sampling.volume import atlas_volume_paths, load_volumes

    brains, _ = load_volumes(atlas_volume_paths(args.data / "atlas" / "sb-fidon2021"))
    scene_config = dataclasses.replace(
        stage_data("localiser", tiles=True).scene,
        skull_in_mask=True,
        face=args.sim_faces,
        spinal_cord=args.sim_spinal_cord,
    )
    stacks = []
    for case in range(args.sim_cases):
        seed = 5000 + case
        rng = np.random.default_rng(seed)
        brain = brains[int(rng.integers(len(brains)))]
        config = SimulationConfig(
            num_stacks=args.sim_stacks,
            thickness_mm=3.3,
            spacing_mm=3.3,
            in_plane_mm=1.125,
            margin_mm=float(rng.uniform(60.0, 120.0)),
            random_walk_rotation_deg=8.0,
            random_walk_translation_mm=3.0,
            noise=0.03,
            bias_field=0.2,
            signal_void_probability=0.05,
            mask_fraction=args.sim_mask_fraction,
            grazing_ratio=args.sim_grazing_ratio,
            seed=seed,
        )
        for stack in simulate_case(make_scene(brain, scene_config, seed=seed), config).stacks:
            stacks.append((f"case {case}", stack.image, stack.mask.data > 0.5))
    return stacks


# (opening_mm, regrow_mm) settings of part ``opening``; (None, 0) is no opening.
OPENINGS = [
    (None, 0.0),
    *((radius, 0.0) for radius in (4.0, 8.0, 12.0)),
    (6.0, 2.0),
    (8.0, 2.0),
    (8.0, 3.0),
    (8.0, 5.0),
    (10.0, 2.0),
]


def part_opening(args: argparse.Namespace, report: dict) -> list[str]:
    from svr.masking import clean_up_mask

    masker = load_brain_masker(args.mask_model)
    threshold = masker.config.threshold
    cases: list[tuple[str, Image, torch.Tensor]] = []
    for dataset, pairs in datasets(args.data).items():
        for stack_path, mask_path in pairs:
            stack = load_nifti(stack_path)
            cases.append((dataset, stack, mask_on_grid(load_nifti(mask_path), stack)))
    cases += [("held-out simulation", image, truth) for _, image, truth in simval_stacks(args)]
    names = list(dict.fromkeys(name for name, _, _ in cases))
    probabilities = []
    for name, image, _ in cases:
        try:
            probabilities.append(segment_stack(image, masker, name=name).probability.numpy())
        except BrainNotFoundError:
            probabilities.append(None)
    lines = [
        "",
        f"Clean-up settings on the probabilities of `{args.mask_model}` (Dice min / mean):",
        "",
        "| opening / regrow (mm) | " + " | ".join(names) + " |",
        "|---" * (len(names) + 1) + "|",
    ]
    report["opening"] = {}
    for opening, regrow in OPENINGS:
        dice: dict[str, list[float]] = {name: [] for name in names}
        for (name, image, truth), probability in zip(cases, probabilities, strict=True):
            if probability is None:
                dice[name].append(0.0)
                continue
            spacing = image.spacing.double().numpy()
            mask = clean_up_mask(probability > threshold, spacing, opening, regrow)
            dice[name].append(scores(torch.from_numpy(mask), truth)["dice"])
        label = "none" if opening is None else f"{opening:g} / {regrow:g}"
        report["opening"][label] = dice
        cells = [f"{min(v):.3f} / {np.mean(v):.3f}" for v in dice.values()]
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


def part_simval(args: argparse.Namespace, report: dict) -> list[str]:
    stacks = simval_stacks(args)
    convention = "centre-plane" if args.sim_mask_fraction is None else "partial-volume"
    lines = [
        "",
        f"Held-out simulated whole-uterus stacks: {len(stacks)} stacks, {args.sim_cases} scenes"
        f" (faces: {'yes' if args.sim_faces else 'no'}; "
        f"spinal cord: {'yes' if args.sim_spinal_cord else 'no'}; {convention} masks"
        + ("" if args.sim_mask_fraction is None else f", fraction {args.sim_mask_fraction:g}")
        + ("" if args.sim_grazing_ratio is None else f", grazing ratio {args.sim_grazing_ratio:g}")
        + ")",
        "",
        "| model | Dice min | Dice mean | recall min | recall mean | not found |",
        "|---|---|---|---|---|---|",
    ]
    report["simval"] = {}
    for model in args.sim_models.split(","):
        masker = load_brain_masker(model)
        rows, masks, probabilities, found = [], [], [], []
        for name, image, truth in stacks:
            try:
                result = segment_stack(image, masker, name=name)
                mask, probability = result.mask, result.probability
                found.append(True)
            except BrainNotFoundError:
                mask, probability = torch.zeros_like(truth), torch.zeros(truth.shape)
                found.append(False)
            rows.append(scores(mask, truth))
            masks.append(mask)
            probabilities.append(probability)
        results = {model: rows}
        if args.sim_stacks >= 3:  # each scene's stacks fused (scenes where all were found)
            from svr.masking.fuse import fuse_stack_masks

            fused_rows, hard_rows = list(rows), list(rows)
            for case in dict.fromkeys(name for name, _, _ in stacks):
                members = [n for n, (name, _, _) in enumerate(stacks) if name == case]
                if not all(found[n] for n in members):
                    continue
                members_stacks = [stacks[n][1] for n in members]
                members_masks = [masks[n] for n in members]
                fused = fuse_stack_masks(
                    members_stacks,
                    members_masks,
                    3.3,
                    probabilities=[probabilities[n] for n in members],
                )
                hard = fuse_stack_masks(members_stacks, members_masks, 3.3)
                for n, mask, hard_mask in zip(members, fused.masks, hard.masks, strict=True):
                    fused_rows[n] = scores(mask, stacks[n][2])
                    hard_rows[n] = scores(hard_mask, stacks[n][2])
            results[f"{model}, fused"] = fused_rows
            results[f"{model}, fused (mask votes)"] = hard_rows
        for label, part in results.items():
            dice = [r["dice"] for r in part]
            recall = [r["recall"] for r in part]
            missed = sum(1 for r in part if r["dice"] == 0)
            report["simval"][label] = part
            lines.append(
                f"| {label} | {min(dice):.3f} | {np.mean(dice):.3f} | {min(recall):.3f} | "
                f"{np.mean(recall):.3f} | {missed} |"
            )
            print(lines[-1], flush=True)
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--mask-model", default="default")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument(
        "--part",
        choices=["masks", "recon", "all", "simval", "opening", "consistency"],
        default="all",
    )
    parser.add_argument("--sim-cases", type=int, default=8, help="simval: number of scenes")
    parser.add_argument(
        "--sim-stacks",
        type=int,
        default=2,
        help="simval: stacks per scene; with 3 or more, each scene's masks are also fused "
        "(fuse_stack_masks) and scored",
    )
    parser.add_argument(
        "--sim-models", default="default", help="simval: comma-separated models to compare"
    )
    parser.add_argument(
        "--sim-faces", action="store_true", help="simval: heads with faces (SceneConfig.face)"
    )
    parser.add_argument(
        "--sim-spinal-cord",
        action="store_true",
        help="simval: heads end at the skull base (SceneConfig.spinal_cord)",
    )
    parser.add_argument(
        "--sim-mask-fraction",
        type=float,
        help="simval: SimulationConfig.mask_fraction of the true masks (default: centre plane)",
    )
    parser.add_argument(
        "--sim-grazing-ratio",
        type=float,
        help="simval: SimulationConfig.grazing_ratio of the true masks (with --sim-mask-fraction)",
    )
    parser.add_argument("--results", type=Path, help="markdown file to write (+ .json beside)")
    parser.add_argument("--figures", type=Path, help="folder for the figures")
    args = parser.parse_args(argv)
    if args.sim_grazing_ratio is not None and args.sim_mask_fraction is None:
        parser.error("--sim-grazing-ratio needs --sim-mask-fraction")
    torch.set_num_threads(args.threads)
    if args.figures is not None:
        args.figures.mkdir(parents=True, exist_ok=True)
    report: dict = {"mask_model": args.mask_model, "threads": args.threads}
    lines = [f"# Automatic brain masks (`{' '.join(sys.argv)}`)", ""]
    if args.part in ("masks", "all"):
        lines += part_masks(args, report)
    if args.part in ("recon", "all"):
        lines += part_recon(args, report)
    if args.part == "simval":
        lines += part_simval(args, report)
    if args.part == "opening":
        lines += part_opening(args, report)
    if args.part == "consistency":
        lines += part_consistency(args, report)
    if args.results is not None:
        args.results.write_text("\n".join(lines) + "\n")
        args.results.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
