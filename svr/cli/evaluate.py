"""``svr evaluate``: the paper's Table 3 for trained pose networks on held-out volumes or cases."""

from __future__ import annotations

import argparse
import csv
import io
import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, cast

from svr.cli.common import (
    MODEL_HELP,
    CliError,
    HelpFormatter,
    add_common_options,
    add_rotation_option,
    option_errors,
    positive_float,
    positive_int,
    resolve_device,
)

if TYPE_CHECKING:
    import numpy as np
    import torch

    from svr.models.network import SlicePoseNet
    from svr.models.stack_pose import StackPoseNet
    from svr.sampling.slicer import SliceConfig
    from svr.sampling.volume import CanonicalVolume

log = logging.getLogger(__name__)

DESCRIPTION = """\
Evaluate one or more trained slice-pose networks on held-out brain volumes (volume/mask pairs,
the gestational ages of an atlas folder that training held out, or built-in phantoms). Every
checkpoint sees the same slices: --num-slices per volume, cut at random validation poses
(seeded by --seed) that pass the empty-slice rule, with the models' input size and spacing. Each
slice is compared with the slice resampled from the ground-truth volume at the predicted pose
(CC, MSE, PSNR, SSIM) and the pose errors are measured (geodesic distance, Euler angles in
degrees, translation in mm). --output-dir receives summary.md (the paper's Table 3: mean / median
per method, and paired t-tests and Wilcoxon tests between methods), summary.csv, per_slice.csv,
paired_tests.csv, poses.csv (true and predicted pose of every slice), evaluation.json, error
histograms and example slices (worst and median cases by geodesic distance). The Markdown summary
is also printed.

A checkpoint DIR is a checkpoint folder (config.json + model.safetensors), a folder of step_*
checkpoints, a training --output-dir (the last two give their newest checkpoint), or `default`:
the slice-pose model shipped with the package (write ./default for a folder of that name), or
`stack-pose` with --cases. NAME=DIR names the method in the tables; a plain DIR is named after
the folder.

With --cases, the checkpoints are stack-pose models (svr train-stack-pose) measured per slice in
context: each case is a simulated case folder (svr simulate's output: stacks, masks, every
slice's true pose and the ground-truth volume), every stack and interleaved packet is placed by
the network alone, as svr reconstruct --registration cnn starts (before any registration), and
each slice's start is compared with its true canonical pose: the same tables, with slices of
128 x 128 pixels at 1 mm cut from the ground-truth volume for the image metrics; a slice whose
brain area is below --min-brain-fraction of the case's largest is left out.

Atlases: the Fidon 2021 spina bifida atlas (zenodo.org/record/5524312: GA21..GA34 folders with
srr.nii.gz and mask.nii.gz, downloaded to a folder such as atlas/) or any folder laid out alike.

examples:
  svr evaluate --checkpoints runs/phantom --output-dir eval/phantom
  svr evaluate --checkpoints shipped=default mine=runs/se3 --output-dir eval/compare
  svr evaluate --checkpoints se3=runs/se3 posenet=runs/posenet \\
      --atlas-dir atlas/ --only-ga 24 28 32 \\
      --num-slices 500 --thickness 3 --output-dir eval/atlas
  svr simulate --input-volume atlas/GA28/srr.nii.gz --input-mask atlas/GA28/mask.nii.gz \\
      --num-stacks 4 --orientations oblique --rotation-deg 70 --translation-mm 10 \\
      --output-dir cases/ga28
  svr evaluate --checkpoints se3=runs/stack-se3 anchor=runs/stack-anchor \\
      --cases cases/ga28 --output-dir eval/packets
"""

CASE_SLICE_SIZE = (128, 128)
"""Pixels of the slices cut for the image metrics with --cases (at CASE_SLICE_SPACING_MM)."""
CASE_SLICE_SPACING_MM = 1.0

NUM_EXAMPLES = 3  # worst and median cases by geodesic distance shown per method
POSE_COLUMNS = ("r_x", "r_y", "r_z", "t_x", "t_y", "t_z")


@dataclass
class _Method:
    """A checkpoint to evaluate: its label, folder and network (in eval mode)."""

    name: str
    folder: Path
    model: SlicePoseNet | StackPoseNet


@dataclass
class _VolumeSlices:
    """The validation slices of one volume, shared by every method."""

    source: str
    volume: CanonicalVolume
    poses: torch.Tensor  # (N, 6) float64 true poses, on the volume's device
    slices: torch.Tensor  # (N, H, W) float32 ground-truth slices, on the volume's device


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr evaluate``."""
    p = subparsers.add_parser(
        "evaluate",
        help="Table-3 evaluation of trained checkpoints",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--checkpoints",
        nargs="+",
        required=True,
        metavar="[NAME=]DIR",
        help="models to compare, each labelled NAME (default: the folder name); DIR is "
        f"{MODEL_HELP}",
    )
    p.add_argument("--output-dir", required=True, help="the report folder to create")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output-dir")
    data = p.add_argument_group("evaluation volumes (default: built-in phantoms)")
    data.add_argument("--atlas-dir", help="folder of GA*/srr.nii.gz + GA*/mask.nii.gz volumes")
    data.add_argument(
        "--only-ga",
        type=float,
        nargs="+",
        default=None,
        help="gestational ages (weeks) of --atlas-dir to evaluate on (training's --hold-out); "
        "default: all",
    )
    data.add_argument("--input-volumes", nargs="*", default=[], help="volume files")
    data.add_argument("--input-masks", nargs="*", default=[], help="their masks, in order")
    data.add_argument(
        "--cases",
        nargs="+",
        default=[],
        metavar="DIR",
        help="simulated case folders (svr simulate): evaluate stack-pose checkpoints per slice, "
        "each slice placed by its packet (see above); not with the options above",
    )
    data.add_argument(
        "--phantom-ga",
        type=positive_float,
        nargs="+",
        default=[26.0, 30.0],
        help="gestational ages of built-in phantoms, without other volumes (training's default "
        "phantoms are 24, 28 and 32 weeks)",
    )
    slices = p.add_argument_group("validation slices")
    slices.add_argument("--num-slices", type=positive_int, default=200, help="slices per volume")
    add_rotation_option(slices)
    slices.add_argument(
        "--thickness",
        type=positive_float,
        default=None,
        help="slice thickness in mm (Gaussian PSF); default: thin slices",
    )
    slices.add_argument(
        "--min-brain-fraction",
        type=float,
        default=0.1,
        help="redraw poses whose slice has a smaller fraction of pixels in the brain mask (with "
        "--cases: leave out slices whose brain area is below this fraction of the case's largest)",
    )
    p.add_argument("--batch-size", type=positive_int, default=64, help="slices per forward pass")
    add_common_options(p)


def _parse_checkpoint_specs(specs: list[str]) -> list[tuple[str, str]]:
    """``[NAME=]DIR`` arguments as (name, DIR) pairs with distinct names."""
    named = []
    for spec in specs:
        name, sep, folder = spec.partition("=")
        if not sep:
            name, folder = Path(spec).resolve().name, spec
        if not name or not folder:
            raise CliError(f"--checkpoints: {spec!r} is not NAME=DIR or DIR")
        named.append((name, folder))
    names = [name for name, _ in named]
    duplicates = sorted({name for name in names if names.count(name) > 1})
    if duplicates:
        raise CliError(
            f"--checkpoints: method names must differ, {', '.join(duplicates)} appear twice "
            "(label them NAME=DIR)"
        )
    return named


def _load_method(name: str, spec: str, device: str, stack_pose: bool) -> _Method:
    """Load the network of a ``--checkpoints`` DIR onto ``device``, in eval mode.

    Args:
        name: The method's label.
        spec: Its ``DIR``.
        device: Where to put it.
        stack_pose: Whether a stack-pose model is expected (``--cases``), or a slice-pose one.
    """
    from svr.models.checkpoint import CheckpointError, resolve_model_path
    from svr.models.predict import load_any_pose_model, pose_model_kind
    from svr.models.stack_pose import STACK_POSE_MODEL, stack_pose_model_path

    try:
        kind = pose_model_kind(spec)
        folder = stack_pose_model_path() if spec == STACK_POSE_MODEL else resolve_model_path(spec)
        if stack_pose != (kind == "stack-pose"):
            wanted = "a stack-pose model (with --cases)" if stack_pose else "a slice-pose model"
            hint = "" if stack_pose else "; evaluate stack-pose models per slice with --cases"
            raise CliError(f"--checkpoints: {folder} is a {kind} model, expected {wanted}{hint}")
        model = load_any_pose_model(folder, device)
    except CheckpointError as err:
        raise CliError(f"--checkpoints: {err}") from err
    log.info("%s: %s (%s)", name, folder, model.config.representation)
    return _Method(name, folder, model)


def _common_geometry(methods: list[_Method]) -> tuple[tuple[int, int], float]:
    """The input size and spacing that every model shares.

    Raises:
        CliError: If the models differ in either.
    """
    configs = {m.name: cast("SlicePoseNet", m.model).config for m in methods}
    geometry = {name: (c.input_size, c.spacing_mm) for name, c in configs.items()}
    if len(set(geometry.values())) > 1:
        listed = ", ".join(
            f"{name} {size[0]}x{size[1]} px at {spacing:g} mm"
            for name, (size, spacing) in geometry.items()
        )
        raise CliError(
            f"--checkpoints: the models must share input size and spacing to see the same "
            f"slices, got {listed}"
        )
    return next(iter(geometry.values()))


def _volumes(args: argparse.Namespace) -> tuple[list[CanonicalVolume], list[str]]:
    """The evaluation volumes named by the options, and a name for each."""
    from svr.sampling.volume import VolumeSourceError, atlas_volume_paths, load_volumes

    if len(args.input_volumes) != len(args.input_masks):
        raise CliError(
            f"--input-volumes ({len(args.input_volumes)}) and --input-masks "
            f"({len(args.input_masks)}) must pair up"
        )
    if args.only_ga is not None and not args.atlas_dir:
        raise CliError("--only-ga needs --atlas-dir")
    pairs = [(Path(v), Path(m)) for v, m in zip(args.input_volumes, args.input_masks, strict=True)]
    if args.atlas_dir:
        try:
            pairs += atlas_volume_paths(args.atlas_dir, only=args.only_ga)
        except VolumeSourceError as err:
            if err.missing_ages:
                ages = " ".join(f"{ga:g}" for ga in err.missing_ages)
                raise CliError(
                    f"--only-ga {ages}: no such GA*/srr.nii.gz in {args.atlas_dir}"
                ) from err
            raise CliError(f"--atlas-dir: {err}") from err
    return load_volumes(pairs, phantom_ages=args.phantom_ga)


def _validation_slices(
    volume: CanonicalVolume,
    source: str,
    config: SliceConfig,
    args: argparse.Namespace,
    generator: torch.Generator,
) -> _VolumeSlices:
    """Random validation poses of one volume that pass the empty-slice rule, and their slices."""
    from svr.sampling.poses import draw_validation_poses
    from svr.sampling.slicer import sample_slices

    try:
        poses = draw_validation_poses(
            volume, args.num_slices, config, generator, args.rotation, args.min_brain_fraction
        )
    except ValueError as err:
        raise CliError(f"{source}: {err} (--min-brain-fraction)") from err
    return _VolumeSlices(source, volume, poses, sample_slices(volume.image, poses, config).float())


def _predict(method: _Method, slices: torch.Tensor, batch_size: int) -> torch.Tensor:
    """(N, 6) a slice-pose method's predicted poses of (N, H, W) slices, in batches."""
    import torch

    model = cast("SlicePoseNet", method.model)
    return torch.cat(
        [model.predict_poses(batch.unsqueeze(1)) for batch in torch.split(slices, batch_size)]
    )


def _example_indices(geodesic: np.ndarray) -> list[int]:
    """The slices with the largest geodesic errors, then those around the median."""
    import numpy as np

    order = np.argsort(geodesic, kind="stable")
    worst = order[::-1][:NUM_EXAMPLES].tolist()
    start = max(0, len(order) // 2 - NUM_EXAMPLES // 2)
    median = [i for i in order[start : start + NUM_EXAMPLES].tolist() if i not in worst]
    return worst + median


def _examples(
    data: list[_VolumeSlices],
    per_slice: dict[str, np.ndarray],
    predicted: torch.Tensor,
    config: SliceConfig,
) -> tuple[np.ndarray, np.ndarray]:
    """Ground-truth and predicted-pose slices of a method's worst and median cases."""
    import numpy as np
    import torch

    from svr.sampling.slicer import sample_slices

    volume_of = np.concatenate([np.full(len(d.poses), v) for v, d in enumerate(data)])
    first = np.cumsum([0] + [len(d.poses) for d in data])
    truth, resampled = [], []
    for i in _example_indices(per_slice["geodesic"]):
        d, j = data[volume_of[i]], i - first[volume_of[i]]
        truth.append(d.slices[j].cpu().numpy())
        pose = predicted[i : i + 1].to(d.volume.image.data.device, torch.float64)
        resampled.append(sample_slices(d.volume.image, pose, config)[0].float().cpu().numpy())
    return np.stack(truth), np.stack(resampled)


def _poses_csv(data: list[_VolumeSlices], predicted: dict[str, torch.Tensor]) -> str:
    """CSV of the true pose (``poses = true``) and each method's prediction of every slice."""
    import torch

    sources = [d.source for d in data for _ in range(len(d.poses))]
    true = torch.cat([d.poses.cpu() for d in data])
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(["poses", "slice", "volume", *POSE_COLUMNS])
    for label, poses in {"true": true, **predicted}.items():
        for i, pose in enumerate(poses.double().tolist()):
            writer.writerow([label, i, sources[i], *(format(x, ".10g") for x in pose)])
    return buffer.getvalue()


_OPTIONS = {"thickness_mm": "--thickness"}
"""The option behind each SliceConfig field it sets (:func:`~svr.cli.common.option_errors`)."""


def _case_slices(
    args: argparse.Namespace, methods: list[_Method], config: SliceConfig
) -> tuple[list[_VolumeSlices], dict[str, list[torch.Tensor]]]:
    """Each case's slices with enough brain at their true poses, and each method's starts.

    A slice is kept where its brain area at its true pose is at least ``--min-brain-fraction``
    of the case's largest (the rule scales with the brain, whatever its age).
    """
    from svr.geometry import se3_to_vector
    from svr.image import Image
    from svr.reconstruction.config import ReconstructionConfig
    from svr.reconstruction.initialisation.case_evaluation import (
        CaseError,
        load_case,
        packet_starts,
    )
    from svr.sampling.slicer import sample_slices

    recon = ReconstructionConfig()  # the packets and restarts that reconstruction uses
    data: list[_VolumeSlices] = []
    starts: dict[str, list[torch.Tensor]] = {m.name: [] for m in methods}
    for folder in args.cases:
        try:
            case = load_case(folder)
        except CaseError as err:
            raise CliError(f"--cases: {err}") from err
        truth = se3_to_vector(case.truth)
        slices = sample_slices(case.volume.image, truth, config).float()
        mask = Image(case.volume.mask.float(), case.volume.image.affine)
        brain = sample_slices(mask, truth, config)
        area = (brain > 0.5).flatten(1).float().sum(1)
        keep = area >= args.min_brain_fraction * area.max().clamp_min(1.0)
        if not bool(keep.any()):
            raise CliError(f"--cases: {folder}: no slice of the brain in its stacks")
        data.append(_VolumeSlices(str(folder), case.volume, truth[keep], slices[keep]))
        for method in methods:
            model = cast("StackPoseNet", method.model)
            placed = packet_starts(model, case, recon.packets, recon.initialisation.restart_deg)
            starts[method.name].append(se3_to_vector(placed)[keep])
        log.info("%s: %d of %d slices evaluated", case.name, int(keep.sum()), len(keep))
    return data, starts


def run(args: argparse.Namespace) -> int:
    """Run ``svr evaluate``."""
    import numpy as np
    import torch

    from svr.files import atomic_write_text, check_output_path
    from svr.models.evaluation import EvalConfig, evaluate_poses, write_report
    from svr.sampling.slicer import SliceConfig

    if not 0 <= args.min_brain_fraction < 1:
        raise CliError(f"--min-brain-fraction must be in [0, 1), got {args.min_brain_fraction}")
    if args.cases and (args.atlas_dir or args.input_volumes or args.input_masks):
        raise CliError("--cases: give either --cases or volumes (--atlas-dir, --input-volumes)")
    out = check_output_path(args.output_dir, args.overwrite)
    device = resolve_device(args.device)
    named = _parse_checkpoint_specs(args.checkpoints)
    cases = bool(args.cases)
    methods = [_load_method(name, spec, device, cases) for name, spec in named]
    if cases:
        size, spacing = CASE_SLICE_SIZE, CASE_SLICE_SPACING_MM
    else:
        size, spacing = _common_geometry(methods)
    with option_errors(_OPTIONS):  # size and spacing are the models'
        config = SliceConfig(size=size, spacing_mm=spacing, thickness_mm=args.thickness)
    if cases:
        data, starts = _case_slices(args, methods, config)
    else:
        volumes, sources = _volumes(args)
        generator = torch.Generator().manual_seed(args.seed)
        data = [
            _validation_slices(volume.to(device), source, config, args, generator)
            for volume, source in zip(volumes, sources, strict=True)
        ]
        starts = {m.name: [_predict(m, d.slices, args.batch_size) for d in data] for m in methods}
    eval_config = EvalConfig(slice=config)
    results: dict[str, dict[str, np.ndarray]] = {}
    predicted: dict[str, torch.Tensor] = {}
    for method in methods:
        per_volume = [
            evaluate_poses(d.volume, d.poses, pred, eval_config, d.slices)
            for d, pred in zip(data, starts[method.name], strict=True)
        ]
        poses = [pred.cpu() for pred in starts[method.name]]
        results[method.name] = {
            key: np.concatenate([r[key] for r in per_volume]) for key in per_volume[0]
        }
        predicted[method.name] = torch.cat(poses)
        log.info(
            "%s: median geodesic %.3f",
            method.name,
            float(np.median(results[method.name]["geodesic"])),
        )
    examples = {
        name: _examples(data, per_slice, predicted[name], config)
        for name, per_slice in results.items()
    }
    write_report(results, out, args.overwrite, examples=examples)
    atomic_write_text(out / "poses.csv", _poses_csv(data, predicted))
    info = {
        "checkpoints": {m.name: str(m.folder) for m in methods},
        "volumes": [d.source for d in data],
        "slices_per_volume": [len(d.poses) for d in data] if cases else args.num_slices,
        "rotation": None if cases else args.rotation,
        "input_size": list(size),
        "spacing_mm": spacing,
        "thickness_mm": args.thickness,
        "min_brain_fraction": args.min_brain_fraction,
        "seed": None if cases else args.seed,
        "cases": cases,
    }
    atomic_write_text(out / "evaluation.json", json.dumps(info, indent=1) + "\n")
    total = sum(len(d.poses) for d in data)
    what = "cases" if cases else "volumes"
    print(f"wrote {out}: {len(methods)} methods on {total} slices from {len(data)} {what}\n")
    print((out / "summary.md").read_text(encoding="utf-8"), end="")
    return 0
