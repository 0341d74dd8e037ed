"""Per-stack canonical poses before any registration: learned stack-pose model vs classical chain.

Stacks measured (each on its own; no stack helps another):

* **held-out ages** (default GA 24, 28, 32; the model never saw them): ``--cases-per-age`` cases of
  ``--stacks-per-case`` stacks each, simulated here at uniformly random orientations (so a fetus
  that turned between stacks is the rule), real fetal motion at 0.3-1.0 of its recorded size,
  thickness 2.5-4.5 mm, in-plane 1 mm, bias field and noise; the simulator's slice masks
  (with ``--loose-masks MM``: loosened as an automatic mask of a whole-uterus scan is,
  :func:`svr.sampling.artefacts.loose_mask`, the same draw for every model);
* **the procedural phantom** (``--phantom-ages``, default GA 28), simulated alike: a brain the
  model never saw and the atlas does not match;
* **the bench cases** (``sb24-large``, ``sb28-moderate``) with their own masks.

Methods, each giving one scanner -> canonical frame per stack:

* ``axes+oracle``: the mask-axis hypothesis nearest the truth (the coarse step's best case);
* ``axes+atlas``: the classical chain, the hypothesis whose atlas agreement (NCC of the stack with
  an atlas of a neighbouring age sampled at the hypothesis; ``--atlas-age-offset``) is highest;
* ``learned``: every hypothesis refined by the network, the best-scored kept, then refined again
  from itself and six starts turned 10 degrees about the canonical axes, the robust mean of the
  seven kept (:func:`svr.models.stack_pose.estimate_stack_pose`);
* ``learned, no restarts``: the same without the restarts (``restart_deg=0``; ``learned`` until
  2026-11-27);
* ``axes+atlas+fit``: that hypothesis refined by rigid registration of the stack's masked voxels
  to the atlas (:func:`svr.models.stack_pose.fit_to_atlas`): the classical estimate in full;
* ``learned+atlas``: the refined hypotheses, chosen by atlas agreement;
* ``learned+atlas+fit``: what ``--registration cnn`` did with a model and an atlas until
  2026-11-27: the model's choice, then the atlas fit where it stays within 15 degrees of it
  (``estimate_stack_pose(model, ..., atlas=...)``);
* ``learned+packets``: the learned frame, then each interleaved packet (from the acquisition
  order) placed on its own (:func:`svr.models.stack_pose.estimate_packet_poses`), the stack's
  pose the robust mean of its slices' packet frames;
* ``learned+atlas slices``: the learned frame, then each slice registered on its own to the atlas,
  the stack's pose the robust mean of its slices', kept where the slices match the atlas
  (:func:`svr.reconstruction.initialisation.atlas_slices.fit_slices_to_atlas`; what ``svr predict
  --atlas-volume`` does with a model).

Errors: the rotation angle between the estimated and the true stack pose (the robust mean of the
slices' true canonical poses, :func:`svr.sampling.blocks.stack_pose_from_slices`) and the distance
between the estimated and true canonical positions of the stack's centre. A stack pose is only as
well defined as the stack is rigid: each stack's **spread** is the median angle between the stack
pose implied by each of its slices (``T_k o (F^-1 N_k)^-1``) and the stack pose, and the table
also gives the share within 10 degrees among the stacks whose spread is at most 10 degrees (those
where "the stack's pose" is defined to within the target at all). With ``--k`` it also
measures blocks of k neighbouring central slices (and one interleaved packet) refined from the
truth turned by ``--k-start-deg`` about a random axis and shifted 5 mm: accuracy against k.
The misses of ``learned`` (over 10 degrees) are broken down per group: by 10-30 degrees or
more, whose spread is above 10 degrees, and how far the nearest of the learned frame's three
front-back twins (turned 180 degrees about a canonical axis) is from the truth, which says
whether testing the twins could rescue them. Each interleaved packet is also scored against its
own true pose (the robust mean of its slices'), by its own estimate and by its stack's frame,
for the stacks whose spread is at most and above 10 degrees.
Last, the best of the estimates per stack chosen by the truth (:data:`CHOOSABLE`): the most
that any rule choosing among them could place within 10 degrees.

Run from the repository root::

    python benchmarks/bench_learned_stack_poses.py --model CHECKPOINT_OR_MODEL_FOLDER
        [--threads 2] [--cases-per-age 4] [--k 1 2 4 8 16] [--results PATH.md]
        [--atlas FAMILY] [--fit-atlas ANOTHER_FAMILY] [--atlas-slices-min-ncc -1]

``--atlas`` is the family the stacks are simulated from (and, by default, the atlas the
atlas-based estimates use); ``--fit-atlas`` gives those estimates another family's atlas, as a
user scanning a brain unlike any atlas would.
"""

from __future__ import annotations

import argparse
import json
import math
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from bench_common import ATLAS, MOTION, SHARED, neighbour_atlas, true_slice_poses

from svr.geometry import half_turns, rotation_angle, se3_compose, se3_inverse, so3_exp
from svr.geometry.averaging import robust_mean_pose
from svr.image import Image, load_nifti, voxel_to_world
from svr.models.stack_pose import load_stack_pose_model
from svr.reconstruction.atlas_fit import atlas_agreement
from svr.reconstruction.initialisation.atlas_slices import (
    ATLAS_SLICES_MIN_NCC,
    AtlasSliceConfig,
    fit_slices_to_atlas,
)
from svr.reconstruction.initialisation.stack_pose import (
    estimate_packet_poses,
    estimate_stack_pose,
    mask_axis_hypotheses,
    refine_transforms,
)
from svr.sampling.artefacts import loose_mask
from svr.sampling.blocks import (
    coarsen_stack,
    implied_stack_poses,
    packet_index,
    stack_frame,
    stack_pose_from_slices,
)
from svr.sampling.motion import load_trajectories
from svr.sampling.phantom import gestational_age_config, make_phantom
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import (
    CanonicalVolume,
    atlas_volume_paths,
    canonicalize,
    load_canonical_volume,
)


def rotation_deg(a: torch.Tensor, b: torch.Tensor) -> float:
    """Angle between the rotations of two (4, 4) transforms, degrees."""
    return math.degrees(rotation_angle(a, b))


def nearest_twin_deg(pose: torch.Tensor, truth: torch.Tensor) -> float:
    """Angle (degrees) between the truth and the nearest front-back twin of a canonical pose.

    The twins are the (4, 4) pose turned by 180 degrees about each canonical axis
    (:func:`svr.geometry.half_turns`).
    """
    twins = se3_compose(half_turns(), pose.expand(3, 4, 4))
    return min(rotation_deg(twin, truth) for twin in twins)


SPREAD_LIMIT_DEG = 10.0
"""Stacks whose slices spread more than this from their stack pose have no pose within 10 deg."""


def median_angle_deg(poses: torch.Tensor, pose: torch.Tensor) -> float:
    """Median angle (degrees) between (N, 4, 4) poses and one (4, 4) pose."""
    return float(np.median([rotation_deg(p, pose) for p in poses]))


def spread_deg(slice_poses: torch.Tensor, stack, pose: torch.Tensor) -> float:
    """Median angle (degrees) between the stack poses implied by each slice and the stack pose."""
    return median_angle_deg(implied_stack_poses(slice_poses, stack), pose)


METHODS = (
    "axes+oracle",
    "axes+atlas",
    "axes+atlas+fit",
    "learned",
    "learned, no restarts",
    "learned+atlas",
    "learned+atlas+fit",
    "learned+packets",
    "learned+atlas slices",
)
"""Every estimate the bench can measure (``--methods``; all by default)."""

CHOOSABLE = tuple(method for method in METHODS if method != "axes+oracle")
"""The estimates a rule could choose among per stack (``axes+oracle`` is chosen by the truth)."""


def best_of_within(rows: list[dict], methods: Sequence[str], limit_deg: float = 10.0) -> int:
    """How many stacks have at least one of ``methods`` within ``limit_deg`` of the truth.

    The share of stacks that any rule choosing among those estimates per stack could place
    within the limit: a bound, the choice made by the truth.
    """
    return sum(any(r[m]["rot_deg"] <= limit_deg for m in methods) for r in rows)


def held_out_stacks(args, trajectories) -> list[dict]:
    """Simulated stacks from the held-out ages (and the phantom), with their true poses."""
    rng = np.random.default_rng(args.seed)
    out = []
    sources = []
    for age in args.ages:
        (vol_path, mask_path), *_ = atlas_volume_paths(args.atlas, only=(age,))
        sources.append((age, "held-out", load_canonical_volume(vol_path, mask_path)))
    for age in args.phantom_ages:
        image, mask = make_phantom(gestational_age_config(age))
        sources.append((age, "phantom", canonicalize(image, mask)))
    for age, kind, volume in sources:
        for c in range(args.cases_per_age):
            thickness = float(rng.uniform(2.5, 4.5))
            config = SimulationConfig(
                num_stacks=args.stacks_per_case,
                orientations="random",
                thickness_mm=thickness,
                in_plane_mm=1.0,
                motion="trajectories",
                motion_path=str(args.motion),
                motion_scale=float(rng.uniform(0.3, 1.0)),
                noise=0.03,
                bias_field=0.2,
                mask_fraction=0.5,
                grazing_ratio=0.5,
                seed=int(rng.integers(2**31 - 1)),
            )
            case = simulate_case(volume, config, trajectories=trajectories)
            to_canonical = torch.eye(4, dtype=torch.float64)
            to_canonical[:3, 3] = -volume.centre_mm.double()
            for s, stack in enumerate(case.stacks):
                truth = se3_compose(to_canonical[None], stack.atlas_poses)
                image, exact = stack.image, stack.mask.data > 0.5
                mask, dice = exact, 1.0
                if args.loose_masks > 0:  # an automatic mask's errors, the same for every model
                    draws = torch.Generator().manual_seed(args.seed * 1_000 + len(out))
                    mask, data = loose_mask(
                        exact, image.data, image.spacing, args.loose_masks, draws
                    )
                    image = Image(data, image.affine)
                    dice = float(2 * (mask & exact).sum() / (mask.sum() + exact.sum()))
                out.append(
                    {
                        "name": f"{kind}-GA{age:g}-case{c}-stack{s}",
                        "group": (
                            f"held-out GA {', '.join(f'{a:g}' for a in args.ages)}"
                            if kind == "held-out"
                            else f"phantom GA {', '.join(f'{a:g}' for a in args.phantom_ages)}"
                        ),
                        "age": age,
                        "image": image,
                        "mask": mask,
                        "pose": stack_pose_from_slices(truth, stack.image),
                        "slice_poses": truth,
                        "acquisition": stack.acquisition_index,
                        "mask_dice": dice,
                    }
                )
    return out


def bench_stacks(args) -> list[dict]:
    """The bench cases' stacks with their true poses."""
    out = []
    for name in args.bench:
        case = args.data / name
        info = json.loads((case / "case.json").read_text(encoding="utf-8"))
        truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))["stacks"]
        centre = torch.tensor(info["atlas_centre_mm"], dtype=torch.float64)
        age = float(info["source"].split("GA")[1][:2])
        for entry in truth:
            file = Path(entry["file"]).name
            image = load_nifti(case / "stacks" / file)
            mask = load_nifti(case / "masks" / file.replace(".nii.gz", "_mask.nii.gz"))
            poses = true_slice_poses(entry["slices"], "atlas", centre)
            out.append(
                {
                    "name": f"{name}-{file.split('.')[0]}",
                    "group": name,
                    "age": age,
                    "image": image,
                    "mask": mask.data > 0.5,
                    "pose": stack_pose_from_slices(poses, image),
                    "slice_poses": poses,
                    "acquisition": torch.tensor([s["acq_index"] for s in entry["slices"]]),
                }
            )
    return out


def summarise(rows: list[dict], method: str) -> dict:
    rot = np.array([r[method]["rot_deg"] for r in rows])
    cen = np.array([r[method]["centre_mm"] for r in rows])
    rigid = np.array([r["spread_deg"] <= SPREAD_LIMIT_DEG for r in rows])
    return {
        "rigid_stacks": int(rigid.sum()),
        "within10_rigid": float((rot[rigid] <= 10).mean()) if rigid.any() else float("nan"),
        "stacks": len(rows),
        "median_deg": float(np.median(rot)),
        "p90_deg": float(np.percentile(rot, 90)),
        "within10": float((rot <= 10).mean()),
        "within30": float((rot <= 30).mean()),
        "median_centre_mm": float(np.median(cen)),
    }


def _progress_line(name: str, row: dict, methods: Sequence[str]) -> str:
    """The line printed per stack: every estimate's error (the full line with every method)."""
    if set(methods) != set(METHODS):
        errors = "  ".join(f"{m} {row[m]['rot_deg']:6.1f}" for m in methods)
        return f"{name:28s} {errors}  ({row.get('seconds', float('nan')):.2f} s)"
    fitted = row["learned+atlas slices"]
    return (
        f"{name:28s} oracle {row['axes+oracle']['rot_deg']:6.1f}  atlas "
        f"{row['axes+atlas']['rot_deg']:6.1f}  fit {row['axes+atlas+fit']['rot_deg']:6.1f} "
        f"{row['axes+atlas+fit']['centre_mm']:5.1f} mm  "
        f"learned {row['learned']['rot_deg']:6.1f} deg "
        f"(no restarts {row['learned, no restarts']['rot_deg']:6.1f}) "
        f"{row['learned']['centre_mm']:5.1f} mm  learned+atlas "
        f"{row['learned+atlas']['rot_deg']:6.1f}  "
        f"learned+atlas+fit {row['learned+atlas+fit']['rot_deg']:6.1f}  "
        f"learned+packets {row['learned+packets']['rot_deg']:6.1f}  "
        f"learned+atlas slices {fitted['rot_deg']:6.1f} "
        f"(NCC {fitted['ncc']:.2f}{', kept' if fitted['kept'] else ''})  "
        f"({row['seconds']:.2f} s, classical {row['classical_seconds']:.2f} s)"
    )


def _packet_rows(item: dict, packets, packet_of, learned_pose, frame_of) -> list[dict]:
    """Each packet's errors against its own true pose (its slices' robust mean).

    By its own estimate and by the stack's: where the fetus moved within the stack, a packet's
    pose is defined where the stack's is not.
    """
    image = item["image"]
    implied = implied_stack_poses(item["slice_poses"], image)
    out = []
    for p in range(int(packet_of.max()) + 1):
        own = implied[packet_of == p]
        packet_truth = stack_pose_from_slices(item["slice_poses"], image, packet_of == p)
        out.append(
            {
                "rot_deg": rotation_deg(
                    se3_compose(packets.to_canonical[p], frame_of), packet_truth
                ),
                "stack_rot_deg": rotation_deg(learned_pose, packet_truth),
                "spread_deg": median_angle_deg(own, packet_truth),
            }
        )
    return out


def measure_stack(item: dict, model, args, atlas_for) -> dict:
    """One stack's row: each estimate of ``args.methods`` against the truth (and timings)."""
    methods = set(args.methods)
    image, mask, truth = item["image"], item["mask"], item["pose"]
    frame_of = stack_frame(image)
    row = {
        "name": item["name"],
        "group": item["group"],
        "spread_deg": spread_deg(item["slice_poses"], image, truth),
    }

    def record(method: str, frame: torch.Tensor) -> None:
        if method not in methods:
            return
        pose = se3_compose(frame, frame_of)
        row[method] = {
            "rot_deg": rotation_deg(pose, truth),
            "centre_mm": float((pose[:3, 3] - truth[:3, 3]).norm()),
        }

    coarse, fractions = coarsen_stack(image, mask, model.config.in_plane_mm)
    idx = torch.nonzero(fractions > 0.5).to(torch.float64)
    starts = mask_axis_hypotheses(voxel_to_world(coarse.affine, idx))
    errors = [rotation_deg(se3_compose(f, frame_of), truth) for f in starts]
    record("axes+oracle", starts[int(np.argmin(errors))])
    needs_atlas = {"axes+atlas", "axes+atlas+fit", "learned+atlas", "learned+atlas+fit"}
    atlas = atlas_for(item["age"]) if methods & (needs_atlas | {"learned+atlas slices"}) else None
    if "axes+atlas" in methods:
        agreement = atlas_agreement(coarse, fractions, starts, atlas)
        record("axes+atlas", starts[int(torch.argmax(agreement))])
    if "axes+atlas+fit" in methods:
        began = time.perf_counter()
        classical = estimate_stack_pose(None, image, mask, atlas=atlas)
        row["classical_seconds"] = time.perf_counter() - began
        record("axes+atlas+fit", classical.to_canonical)
    if not methods & {m for m in METHODS if m.startswith("learned")}:
        return row
    began = time.perf_counter()
    estimate = estimate_stack_pose(model, image, mask, args.iterations, restart_deg=10.0)
    row["seconds"] = time.perf_counter() - began
    record("learned", estimate.to_canonical)
    learned_pose = se3_compose(estimate.to_canonical, frame_of)
    if "learned" in methods:
        row["learned"]["twin_deg"] = nearest_twin_deg(learned_pose, truth)
    # Without the restarts the estimate is the best-scored refined hypothesis.
    record("learned, no restarts", estimate.hypotheses[int(torch.argmax(estimate.scores))])
    if "learned+packets" in methods:
        packet_of = packet_index(item["acquisition"])
        packets = estimate_packet_poses(model, image, mask, estimate.to_canonical, packet_of)
        record("learned+packets", robust_mean_pose(packets.to_canonical[packet_of]))
        row["packets"] = _packet_rows(item, packets, packet_of, learned_pose, frame_of)
    if "learned+atlas" in methods:
        refined_agreement = atlas_agreement(coarse, fractions, estimate.hypotheses, atlas)
        record("learned+atlas", estimate.hypotheses[int(torch.argmax(refined_agreement))])
    if "learned+atlas+fit" in methods:
        both = estimate_stack_pose(
            model, image, mask, args.iterations, atlas=atlas, restart_deg=10.0
        )
        record("learned+atlas+fit", both.to_canonical)
    if "learned+atlas slices" in methods:
        began = time.perf_counter()
        gate = AtlasSliceConfig(min_ncc=args.atlas_slices_min_ncc)
        fitted = fit_slices_to_atlas(image, mask, estimate.to_canonical, atlas, config=gate)
        row["atlas_slices_seconds"] = time.perf_counter() - began
        record("learned+atlas slices", fitted.to_canonical)
        row["learned+atlas slices"].update(ncc=fitted.ncc, kept=fitted.kept)
    return row


def k_accuracy(stacks: list[dict], model, args) -> list[dict]:
    """``--k``: accuracy of blocks of k neighbouring central slices, one packet and all slices.

    Each is refined from the truth turned by ``--k-start-deg`` and shifted 5 mm, per held-out
    stack.
    """
    k_rows: list[dict] = []
    gen = torch.Generator().manual_seed(args.seed)
    for item in stacks:
        if not item["group"].startswith("held-out"):
            continue
        image, fractions = coarsen_stack(item["image"], item["mask"], model.config.in_plane_mm)
        count = image.shape[2]
        frame_true = se3_compose(item["pose"], se3_inverse(stack_frame(item["image"])))
        axis = torch.nn.functional.normalize(
            torch.randn(3, generator=gen, dtype=torch.float64), dim=0
        )
        start = torch.eye(4, dtype=torch.float64)
        start[:3, :3] = so3_exp(axis * math.radians(args.k_start_deg))
        start[:3, 3] = (
            torch.nn.functional.normalize(torch.randn(3, generator=gen, dtype=torch.float64), dim=0)
            * 5.0
        )
        start = se3_compose(start, frame_true)
        subsets = {}
        for k in args.k:
            if k < count:
                present = torch.zeros(count, dtype=torch.bool)
                first = (count - k) // 2
                present[first : first + k] = True
                subsets[str(k)] = present
        order = torch.argsort(item["acquisition"])
        breaks = torch.nonzero(order[1:] < order[:-1]).flatten() + 1
        packet = torch.zeros(count, dtype=torch.bool)
        packet[order[: int(breaks[0]) if len(breaks) else count]] = True
        subsets["packet"] = packet
        subsets["all"] = torch.ones(count, dtype=torch.bool)
        for label, present in subsets.items():
            frames, _ = refine_transforms(
                model, image, fractions, start[None], args.iterations, present
            )
            pose = se3_compose(frames[0], stack_frame(item["image"]))
            k_rows.append(
                {
                    "k": label,
                    "rot_deg": rotation_deg(pose, item["pose"]),
                    "centre_mm": float((pose[:3, 3] - item["pose"][:3, 3]).norm()),
                }
            )
    return k_rows


def report(rows: list[dict], args) -> tuple[list[str], dict]:
    """The results' lines (the table and the notes on what was measured) and the summary."""
    methods = [m for m in ["axes+oracle", *CHOOSABLE] if m in args.methods]
    choosable = [m for m in CHOOSABLE if m in args.methods]
    groups = sorted({r["group"] for r in rows})
    lines = [
        "| stacks | method | n | median (deg) | p90 (deg) | within 10 deg | within 30 deg "
        f"| centre median (mm) | within 10 deg where spread <= {SPREAD_LIMIT_DEG:g} deg (n) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    summary = {}
    for group in groups:
        members = [r for r in rows if r["group"] == group]
        for method in methods:
            s = summarise(members, method)
            summary[f"{group}/{method}"] = s
            lines.append(
                f"| {group} | {method} | {s['stacks']} | {s['median_deg']:.1f} | "
                f"{s['p90_deg']:.1f} | {100 * s['within10']:.0f} % | {100 * s['within30']:.0f} % | "
                f"{s['median_centre_mm']:.1f} | {100 * s['within10_rigid']:.0f} % "
                f"({s['rigid_stacks']}) |"
            )
    lines.append("")
    lines.append("Spread of each group's stacks (median angle of the slices from the stack pose):")
    lines.append("")
    for group in groups:
        spread = np.array([r["spread_deg"] for r in rows if r["group"] == group])
        lines.append(
            f"- {group}: median {np.median(spread):.1f} deg, "
            f"{int((spread > SPREAD_LIMIT_DEG).sum())} of {len(spread)} stacks above "
            f"{SPREAD_LIMIT_DEG:g} deg"
        )
    if "learned" in args.methods:
        lines += _misses(rows, groups)
    if choosable:
        lines += _best_of(rows, groups, choosable)
    if "learned+packets" in args.methods:
        lines += _packets(rows, groups)
    lines += _times(rows, groups, args.threads)
    return lines, summary


def _misses(rows: list[dict], groups: list[str]) -> list[str]:
    """The lines on the misses of ``learned``, per group."""
    lines = []
    lines.append("")
    lines.append(
        "Misses of `learned` (over 10 deg): by 10-30 deg / more, how many of each in stacks whose "
        f"spread is above {SPREAD_LIMIT_DEG:g} deg, and the nearest front-back twin of the gross "
        "ones (deg from the truth):"
    )
    lines.append("")
    for group in groups:
        members = [r["learned"] | {"spread": r["spread_deg"]} for r in rows if r["group"] == group]
        near = [m for m in members if 10 < m["rot_deg"] <= 30]
        gross = [m for m in members if m["rot_deg"] > 30]
        moved = [sum(m["spread"] > SPREAD_LIMIT_DEG for m in part) for part in (near, gross)]
        gross.sort(key=lambda m: m["twin_deg"])
        twins = ", ".join(f"{m['twin_deg']:.0f}" for m in gross)
        lines.append(
            f"- {group}: {len(near) + len(gross)} of {len(members)}; {len(near)} by 10-30 deg "
            f"({moved[0]} spread), {len(gross)} more ({moved[1]} spread; twins {twins or '-'})"
        )
    return lines


def _best_of(rows: list[dict], groups: list[str], choosable: list[str]) -> list[str]:
    """The lines on the best of the estimates per stack (chosen by the truth), per group."""
    lines = []
    lines.append("")
    lines.append(
        "The best of the estimates per stack, chosen by the truth (the most that a rule choosing "
        f"among {', '.join(f'`{m}`' for m in choosable)} could place within 10 deg):"
    )
    lines.append("")
    for group in groups:
        members = [r for r in rows if r["group"] == group]
        best = best_of_within(members, choosable)
        alone = best_of_within(members, ["learned"]) if "learned" in choosable else "-"
        lines.append(
            f"- {group}: {100 * best / len(members):.1f} % ({best} of {len(members)}; "
            f"`learned` alone {alone})"
        )
    return lines


def _packets(rows: list[dict], groups: list[str]) -> list[str]:
    """The lines on the interleaved packets, per group."""
    lines = []
    lines.append("")
    lines.append(
        "Interleaved packets against their own true poses, each by its own estimate (the "
        "`learned+packets` step) and by its stack's `learned` frame: share within 10 deg, in the "
        f"stacks whose spread is at most / above {SPREAD_LIMIT_DEG:g} deg (packets):"
    )
    lines.append("")
    for group in groups:
        parts = []
        for label, keep in (("<=", False), (">", True)):
            packets = [
                q
                for r in rows
                if r["group"] == group and (r["spread_deg"] > SPREAD_LIMIT_DEG) == keep
                for q in r["packets"]
            ]
            if packets:
                own = np.mean([q["rot_deg"] <= 10 for q in packets])
                by_stack = np.mean([q["stack_rot_deg"] <= 10 for q in packets])
                parts.append(
                    f"spread {label} {SPREAD_LIMIT_DEG:g}: own {100 * own:.0f} %, stack's "
                    f"{100 * by_stack:.0f} % ({len(packets)})"
                )
        lines.append(f"- {group}: " + "; ".join(parts))
    return lines


def _times(rows: list[dict], groups: list[str], threads: int) -> list[str]:
    """The lines on the time per stack and the slices' atlas fits kept (what was measured)."""

    def median_max(key: str) -> str:
        values = np.array([r[key] for r in rows])
        return f"median {np.median(values):.2f} s (max {values.max():.2f} s)"

    parts = []
    if "seconds" in rows[0]:
        parts.append(f"learned estimate {median_max('seconds')}")
    if "classical_seconds" in rows[0]:
        parts.append(f"axes + atlas choice + fit {median_max('classical_seconds')}")
    if "atlas_slices_seconds" in rows[0]:
        parts.append(
            f"the slices' atlas fit after the learned estimate {median_max('atlas_slices_seconds')}"
        )
    lines = []
    if parts:
        lines.append("")
        lines.append(f"Time per stack ({threads} threads): " + "; ".join(parts) + ".")
    if "learned+atlas slices" not in rows[0]:
        return lines
    lines.append("")
    lines.append(
        "`learned+atlas slices` kept the slices' atlas fit (their mean NCC with the atlas "
        "at least the gate) for: "
        + "; ".join(
            f"{group} {sum(r['learned+atlas slices']['kept'] for r in rows if r['group'] == group)}"
            f" of {sum(r['group'] == group for r in rows)}"
            for group in groups
        )
        + "."
    )
    return lines


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True, help="checkpoint or model folder")
    parser.add_argument("--atlas", type=Path, default=ATLAS)
    parser.add_argument("--motion", type=Path, default=MOTION)
    parser.add_argument("--data", type=Path, default=SHARED / "data" / "bench")
    parser.add_argument("--ages", type=float, nargs="*", default=[24.0, 28.0, 32.0])
    parser.add_argument("--phantom-ages", type=float, nargs="*", default=[28.0])
    parser.add_argument("--bench", nargs="*", default=["sb24-large", "sb28-moderate"])
    parser.add_argument("--cases-per-age", type=int, default=4)
    parser.add_argument("--stacks-per-case", type=int, default=3)
    parser.add_argument("--atlas-age-offset", type=float, default=1.0)
    parser.add_argument(
        "--fit-atlas",
        type=Path,
        default=None,
        help="atlas family the atlas-based estimates use (default: --atlas, the cases' own "
        "family; another family measures a user's atlas on a brain unlike it)",
    )
    parser.add_argument(
        "--atlas-slices-min-ncc",
        type=float,
        default=ATLAS_SLICES_MIN_NCC,
        help="the NCC at or above which 'learned+atlas slices' keeps the fit (default: the "
        "library's; -1 keeps every fit)",
    )
    parser.add_argument(
        "--loose-masks",
        type=float,
        default=0.0,
        metavar="MM",
        help="loosen the simulated stacks' masks by up to MM (svr.sampling.artefacts.loose_mask) "
        "and fill the tissue they take in (default: 0, the simulator's masks)",
    )
    parser.add_argument("--iterations", type=int, default=3)
    parser.add_argument("--k", type=int, nargs="*", default=[])
    parser.add_argument("--k-start-deg", type=float, default=20.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--results", type=Path, default=None)
    parser.add_argument(
        "--methods",
        nargs="+",
        choices=METHODS,
        default=list(METHODS),
        metavar="METHOD",
        help="the estimates to measure (default: all; e.g. 'learned' 'learned, no restarts' "
        "for the model alone, seconds per stack)",
    )
    args = parser.parse_args()
    args.methods = [m for m in METHODS if m in args.methods]
    torch.set_num_threads(args.threads)
    model = load_stack_pose_model(args.model)
    trajectories = load_trajectories(args.motion)
    stacks = held_out_stacks(args, trajectories) + bench_stacks(args)
    atlases: dict[tuple[Path, Path], CanonicalVolume] = {}

    def atlas_for(age: float) -> CanonicalVolume:
        paths = neighbour_atlas(age, args.atlas_age_offset, args.fit_atlas or args.atlas)
        if paths not in atlases:
            atlases[paths] = load_canonical_volume(*paths)
        return atlases[paths]

    rows = []
    for item in stacks:
        rows.append(measure_stack(item, model, args, atlas_for))
        print(_progress_line(item["name"], rows[-1], args.methods), flush=True)

    k_rows = k_accuracy(stacks, model, args) if args.k else []
    lines, summary = report(rows, args)
    if args.loose_masks > 0:
        dice = np.array([item["mask_dice"] for item in stacks if "mask_dice" in item])
        lines += [
            "",
            f"Loose masks (--loose-masks {args.loose_masks:g}): Dice with the simulator's masks "
            f"median {np.median(dice):.3f}, 10th-90th percentile {np.percentile(dice, 10):.3f}-"
            f"{np.percentile(dice, 90):.3f}, min {dice.min():.3f} ({len(dice)} stacks).",
        ]
    if k_rows:
        lines += [
            "",
            f"Accuracy against k (refined from the truth turned by {args.k_start_deg:g} deg "
            "and shifted 5 mm):",
            "",
        ]
        lines += [
            "| block | n | median (deg) | within 10 deg | centre median (mm) |",
            "|---|---|---|---|---|",
        ]
        for label in dict.fromkeys(r["k"] for r in k_rows):
            members = [r for r in k_rows if r["k"] == label]
            rot = np.array([r["rot_deg"] for r in members])
            cen = np.array([r["centre_mm"] for r in members])
            lines.append(
                f"| {label} | {len(members)} | {np.median(rot):.1f} | "
                f"{100 * (rot <= 10).mean():.0f} % | "
                f"{np.median(cen):.1f} |"
            )
    text = "\n".join(lines)
    print(text)
    if args.results is not None:
        args.results.parent.mkdir(parents=True, exist_ok=True)
        command = "python benchmarks/bench_learned_stack_poses.py " + shlex.join(sys.argv[1:])
        args.results.write_text(
            f"# Learned stack poses\n\nCommand: `{command}`\n\nModel: `{args.model}`\n\n{text}\n",
            encoding="utf-8",
        )
        args.results.with_suffix(".json").write_text(
            json.dumps({"summary": summary, "rows": rows, "k": k_rows}, indent=1), encoding="utf-8"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
