"""Slice poses as one smooth motion per packet: the trajectory fit on a severe-motion bench case.

On a bench case (default ``sb32-severe``, motion within every stack), every slice's TRUE pose
(``truth_slices.json``, scanner frame) is perturbed as a per-slice pose estimator would: each
slice turned by a set angle (``--noise-deg``, random axis through its centre) and shifted by
``--shift-mm-per-deg`` times that (random direction); a fraction of slices (``--outliers``) is
turned by a further ``--outlier-deg`` as gross outliers. The trajectory of each interleaved
packet (2 per stack) is fitted (:func:`svr.reconstruction.trajectory.fit_slice_trajectory`, the
stacks' own slice geometry as the nominal poses) and the slices' errors against the truth are
compared before and after, with how many planted outliers are flagged.

It also fits the noise-free truth: what a perfect estimate loses by being smoothed, which shows
how smooth the true motion is and decides the default smoothness (``--smoothness`` sweeps it).

Run from the repository root::

    python benchmarks/bench_trajectory.py [--case sb32-severe] [--draws 10] [--threads 1]
        [--results benchmarks/results/trajectory.md]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
from bench_common import SHARED, true_slice_poses, write_results

from svr.geometry import rotation_angle, se3_compose, se3_inverse, vector_to_se3
from svr.image import load_nifti, stack_slice_poses
from svr.reconstruction.acquisition import packet_key
from svr.reconstruction.slices import SliceSet
from svr.reconstruction.trajectory import (
    TrajectoryConfig,
    fit_slice_trajectory,
    fit_trajectory,
    packet_times,
)

PACKETS = 2


def load_case(case: Path) -> tuple[SliceSet, torch.Tensor, list[str]]:
    """The case's slices (true poses, the files' geometry as scanner poses) and acquisition check.

    Returns:
        ``(slices, acq_index, notes)``: a :class:`SliceSet` with 1 x 1 dummy images, the
        truth's (N,) acquisition index of each slice within its stack, and lines on what the
        acquisition order was found to be.
    """
    truth = json.loads((case / "truth_slices.json").read_text(encoding="utf-8"))
    poses, nominal, sid, ks, acq = [], [], [], [], []
    notes = []
    for s, entry in enumerate(truth["stacks"]):
        n = len(entry["slices"])
        poses.append(true_slice_poses(entry["slices"], "scanner"))
        nominal.append(stack_slice_poses(load_nifti(case / entry["file"])))
        if len(nominal[-1]) != n:
            raise SystemExit(f"{entry['file']}: {len(nominal[-1])} planes, {n} true poses")
        index = torch.tensor([x["acq_index"] for x in entry["slices"]])
        expected = torch.from_numpy(np.argsort(np.r_[np.arange(0, n, 2), np.arange(1, n, 2)]))
        notes.append(
            f"{entry['file']}: {n} slices, acquisition order "
            + ("= even k, then odd k" if torch.equal(index, expected) else "NOT even-then-odd")
        )
        sid.append(torch.full((n,), s, dtype=torch.int64))
        ks.append(torch.arange(n))
        acq.append(index)
    T = torch.cat(poses)
    n = len(T)
    slices = SliceSet(
        images=torch.zeros(n, 1, 1),
        masks=torch.ones(n, 1, 1, dtype=torch.bool),
        spacing_mm=torch.ones(n, 2, dtype=torch.float64),
        thickness_mm=torch.ones(n, dtype=torch.float64),
        poses=T,
        frame="scanner",
        stack_ids=torch.cat(sid),
        slice_indices=torch.cat(ks),
        plane_offsets_mm=torch.zeros(n, 2, dtype=torch.float64),
        scanner_poses=torch.cat(nominal),
        stack_names=tuple(e["file"] for e in truth["stacks"]),
    )
    # The packet definition (k % 2, in k order) must give the truth's order in time.
    packet = packet_key(slices, PACKETS)
    time = slices.slice_indices // PACKETS
    rank, acq_all = packet * (len(T) + 1) + time, torch.cat(acq)
    same = all(
        torch.equal(
            torch.argsort(torch.argsort(rank[slices.stack_ids == s])),
            acq_all[slices.stack_ids == s],
        )
        for s in range(len(truth["stacks"]))
    )
    notes.append(
        "packet p = k % 2 acquired in increasing k, packet 0 first: "
        + ("matches every acq_index" if same else "DOES NOT match acq_index")
    )
    return slices, torch.cat(acq), notes


def true_steps(slices: SliceSet, acq: torch.Tensor) -> tuple[np.ndarray, np.ndarray]:
    """The true head motion between slices acquired one after another in a packet.

    The motion of slice ``i`` is ``M_i = T_i o N_i^-1`` (true pose after nominal pose, scanner
    frame). Returns the rotation (degrees) of ``M_i^-1 o M_j`` and the move (mm) of the stack's
    centre under it, for each consecutive pair ``(i, j)`` of a packet.
    """
    M = se3_compose(slices.poses, se3_inverse(slices.scanner_poses))
    rot, shift = [], []
    for s in range(len(slices.stack_names)):
        index = torch.nonzero(slices.stack_ids == s).flatten()
        order = index[torch.argsort(acq[index])]
        centre = slices.scanner_poses[index, :3, 3].mean(0)
        moved = (M[:, :3, :3] @ centre + M[:, :3, 3])[order]
        same = (
            slices.slice_indices[order[1:]] % PACKETS == slices.slice_indices[order[:-1]] % PACKETS
        )
        a, b = order[:-1][same], order[1:][same]
        rot.append(torch.rad2deg(rotation_angle(M[a], M[b])).numpy())
        shift.append((moved[1:] - moved[:-1])[same].norm(dim=-1).numpy())
    return np.concatenate(rot), np.concatenate(shift)


def perturb(
    truth: torch.Tensor,
    rng: np.random.Generator,
    deg: float,
    mm: float,
    fraction: float,
    big: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Noisy poses (turned about and shifted from each slice's centre) and the planted outliers."""
    n = len(truth)
    axis = rng.normal(size=(n, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    shift = rng.normal(size=(n, 3))
    shift /= np.linalg.norm(shift, axis=1, keepdims=True)
    outlier = np.zeros(n, dtype=bool)
    outlier[rng.choice(n, round(fraction * n), replace=False)] = True
    turn = axis * np.radians(deg)
    turn[outlier] = axis[outlier] * np.radians(big)  # the gross error dominates: a fixed angle
    local = vector_to_se3(torch.from_numpy(np.concatenate([turn, 0 * shift], axis=1)))
    noisy = se3_compose(truth, local)
    noisy[:, :3, 3] += torch.from_numpy(shift * mm)
    return noisy, torch.from_numpy(outlier)


def errors(poses: torch.Tensor, truth: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-slice rotation error (degrees) and centre error (mm)."""
    return (
        torch.rad2deg(rotation_angle(poses, truth)),
        (poses[:, :3, 3] - truth[:, :3, 3]).norm(dim=-1),
    )


def q(x: torch.Tensor, p: float) -> float:
    return float(torch.quantile(x, p))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--case", default="sb32-severe")
    parser.add_argument("--draws", type=int, default=10, help="noise draws per level")
    parser.add_argument("--noise-deg", type=float, nargs="+", default=[5.0, 10.0, 15.0])
    parser.add_argument("--shift-mm-per-deg", type=float, default=0.4)
    parser.add_argument("--outliers", type=float, default=0.1, help="fraction of slices")
    parser.add_argument("--outlier-deg", type=float, default=45.0)
    parser.add_argument(
        "--smoothness", type=float, nargs="+", default=[0.01, 0.02, 0.05, 0.1, 0.25, 1.0, 4.0]
    )
    parser.add_argument("--orders", type=int, nargs="+", default=[1, 2], help="penalty orders")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--results", type=Path, default=None)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    slices, acq, notes = load_case(SHARED / "data" / "bench" / args.case)
    truth = slices.poses
    default = TrajectoryConfig()

    def name(order: int, lam: float) -> str:
        mark = " (default)" if (order, lam) == (default.penalty_order, default.smoothness) else ""
        return f"{order}, {lam:g}{mark}"

    out = [f"Case `{args.case}`: {len(truth)} slices, {PACKETS} interleaved packets per stack.", ""]
    out += [f"- {line}" for line in notes]
    rot, shift = true_steps(slices, acq)
    out += [
        f"- The true head motion between slices acquired one after another in a packet "
        f"({len(rot)} pairs): rotation median {np.median(rot):.1f} deg, 90th percentile "
        f"{np.percentile(rot, 90):.1f}, max {rot.max():.1f}; the stack centre moves median "
        f"{np.median(shift):.1f} mm, 90th percentile {np.percentile(shift, 90):.1f} mm.",
    ]

    out += ["", "## The true motion's smoothness: the fit applied to the noise-free truth", ""]
    out += [
        "Residual of the TRUE poses from their fitted trajectory (what a perfect estimate loses by "
        "being smoothed), per penalty order and smoothness, with the stacks' geometry as nominal "
        "poses (transported, the default of `fit_slice_trajectory`) and without (`nominal=None`). "
        "`flagged`: true poses flagged as outliers (thresholds "
        f"{default.outlier_deg:g} deg / {default.outlier_mm:g} mm).",
        "",
        "| order, smoothness | nominal | median deg | p90 deg | max deg | median mm | p90 mm "
        "| flagged |",
        "|---|---|---|---|---|---|---|---|",
    ]
    packet, time = packet_times(slices, PACKETS)
    settings = [(o, lam) for o in args.orders for lam in args.smoothness]
    for order, lam in settings:
        config = TrajectoryConfig(smoothness=lam, penalty_order=order)
        for label, nominal in (("stack", slices.scanner_poses), ("none", None)):
            fit = fit_trajectory(truth, packet, time, config, nominal=nominal)
            deg, mm = errors(fit.poses, truth)
            out.append(
                f"| {name(order, lam)} | {label} | {q(deg, 0.5):.2f} | {q(deg, 0.9):.2f} | "
                f"{float(deg.max()):.2f} | {q(mm, 0.5):.2f} | {q(mm, 0.9):.2f} | "
                f"{int(fit.outlier.sum())}/{len(truth)} |"
            )

    header = (
        "| noise | rot median before / after (ratio) | rot p90 before / after (ratio) "
        "| mm median before / after (ratio) | mm p90 before / after (ratio) | found | false "
        "| outliers |",
        "|---|---|---|---|---|---|---|---|",
    )
    out += ["", "## Noisy estimates before and after the fit (default settings)", ""]
    out += [
        f"Each slice turned by the set angle (random axis through its centre) and shifted by "
        f"{args.shift_mm_per_deg:g} mm per degree (random direction); {args.outliers:.0%} of the "
        f"slices turned by {args.outlier_deg:g} deg instead (planted outliers). {args.draws} draws "
        "per level, all slices of all draws pooled. Errors against the truth: rotation angle "
        "(deg) and slice-centre distance (mm), median / 90th percentile; ratio = after / before. "
        "`found`: planted outliers flagged; `false`: other slices flagged.",
        "",
        f"`outliers`: the planted outliers' rotation error after the fit (before: "
        f"{args.outlier_deg:g} deg), median.",
        "",
        header[0].replace("| noise", "| order, smoothness | noise"),
        "|---" + header[1],
    ]

    def table(config: TrajectoryConfig) -> list[str]:
        rows = []
        for level in args.noise_deg:
            rng = np.random.default_rng(1000 + round(10 * level))
            before, after, flags, planted = [], [], [], []
            for _ in range(args.draws):
                noisy, outlier = perturb(
                    truth, rng, level, level * args.shift_mm_per_deg, args.outliers,
                    args.outlier_deg,
                )  # fmt: skip
                fit = fit_slice_trajectory(slices.with_poses(noisy), PACKETS, config)
                before.append(errors(noisy, truth))
                after.append(errors(fit.poses, truth))
                flags.append(fit.outlier)
                planted.append(outlier)
            b = [torch.cat([x[i] for x in before]) for i in (0, 1)]
            a = [torch.cat([x[i] for x in after]) for i in (0, 1)]
            f, p = torch.cat(flags), torch.cat(planted)
            cells = [
                f"{q(b[i], pct):.2f} / {q(a[i], pct):.2f} ({q(a[i], pct) / q(b[i], pct):.2f})"
                for i in (0, 1)
                for pct in (0.5, 0.9)
            ]
            found = float(f[p].double().mean())
            false = float(f[~p].double().mean())
            rows.append(
                f"{level:g} deg | " + " | ".join(cells)
                + f" | {found:.0%} | {false:.1%} | {q(a[0][p], 0.5):.2f} |"
            )  # fmt: skip
        return rows

    out += [f"| {name(default.penalty_order, default.smoothness)} | " + r for r in table(default)]
    out += [
        "",
        "The sweep (same draws):",
        "",
        header[0].replace("| noise", "| order, smoothness | noise"),
        "|---" + header[1],
    ]
    for order, lam in settings:
        config = TrajectoryConfig(smoothness=lam, penalty_order=order)
        out += [f"| {name(order, lam)} | " + row for row in table(config)]
    text = "\n".join(out)
    print(text)
    if args.results is not None:
        write_results(args.results, "Motion as a trajectory in time", text, " (2026-12-06, CPU)")


if __name__ == "__main__":
    main()
