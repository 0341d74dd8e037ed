"""``svr export-model``: a trained pose checkpoint as a small float16 model folder to share."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from svr.cli.common import (
    CliError,
    HelpFormatter,
    add_common_options,
    check_outputs,
    resolve_device,
)

DESCRIPTION = """\
Export a checkpoint of svr train (a slice-pose model) or svr train-stack-pose (a stack-pose
model; the kind is read from the checkpoint's config) as a model folder to ship or share: the
weights in float16 (at most 10 MB), a config.json with what loading the model needs and its
provenance (the training command, the training data and its licence, the source checkpoint,
the library versions), and a README.md that sums it up. The folder is a model for svr predict
--model (and wherever a model folder is accepted); loading it runs no code. A training run
folder stands for its newest checkpoint. The export runs on the CPU (--device is only checked;
--seed is not used).

examples:
  svr export-model --checkpoint runs/se3 --output-model my-model \\
      --training-command "svr train --output-dir runs/se3 --atlas-dir atlas/ --steps 20000" \\
      --data "sb-fidon2021 atlas (zenodo.org/record/5524312), CC0 1.0"
  svr export-model --checkpoint runs/stack-pose --output-model my-stack-pose \\
      --data "sb-fidon2021 atlas (CC0 1.0); SVoRT fetal motion trajectories (Apache-2.0)"
"""

_CARD = """\
# {kind} model exported by `svr export-model`

Float16 weights (`model.safetensors`) and `config.json` (the model's configuration and its
provenance); give this folder as `svr predict --model`. Loading it runs no code.

- Source: `{source}`{step}.
- Training data: {data}

Training command:

    {command}
"""


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    """Register ``svr export-model``."""
    p = subparsers.add_parser(
        "export-model",
        help="export a trained pose checkpoint as a small float16 model folder",
        description=DESCRIPTION,
        formatter_class=HelpFormatter,
    )
    p.add_argument(
        "--checkpoint",
        required=True,
        metavar="CHECKPOINT_DIR",
        help="a checkpoint folder of svr train or svr train-stack-pose, or a training run folder "
        "(its newest checkpoint)",
    )
    p.add_argument("--output-model", required=True, metavar="MODEL_DIR", help="folder to write")
    p.add_argument(
        "--data",
        required=True,
        metavar="TEXT",
        help="the training data: what it is, its source and its licence",
    )
    p.add_argument(
        "--training-command",
        metavar="COMMAND",
        help="the exact command that trained the model (default: the one the checkpoint records; "
        "svr train-stack-pose records it, svr train does not)",
    )
    p.add_argument("--overwrite", action="store_true", help="replace an existing --output-model")
    add_common_options(p)


def _provenance(args: argparse.Namespace, kind: str, config: dict[str, Any]) -> dict[str, Any]:
    """The model's provenance: the training command, the data, the source's own record of both.

    Raises:
        CliError: If there is no training command (none given, none recorded) or ``--data`` is
            empty.
    """
    command = args.training_command or config.get("command")
    if not command:
        raise CliError(
            f"--training-command: {args.checkpoint} records no training command; give the "
            "command that trained it"
        )
    if not args.data.strip():
        raise CliError("--data: empty; say what the training data is, its source and licence")
    if kind == "stack-pose":
        recorded: Any = config.get("data")
        extra = {"train": config.get("train")}
    else:
        recorded = (config.get("training") or {}).get("data_sources")
        extra = {}
    return {
        "training_command": command,
        "data": {"description": args.data, "recorded": recorded},
        **extra,
    }


def run(args: argparse.Namespace) -> int:
    """Run ``svr export-model``."""
    from svr.files import atomic_write_text
    from svr.models.checkpoint import CHECKPOINT_CONFIG, CheckpointError, resolve_model_path
    from svr.models.predict import pose_model_kind
    from svr.models.pretrained.export import export_model, export_stack_pose_model

    resolve_device(args.device)  # checked as every command checks it; the export needs no device
    check_outputs(
        [("--output-model", args.output_model, None)],
        args.overwrite,
        [("--checkpoint", args.checkpoint)],
    )
    try:
        source = resolve_model_path(args.checkpoint)
    except CheckpointError as err:
        raise CliError(f"--checkpoint: {err}") from err
    kind = pose_model_kind(source.resolve())  # (a path: never the name of a shipped model)
    config = json.loads((source / CHECKPOINT_CONFIG).read_text(encoding="utf-8"))
    provenance = _provenance(args, kind, config)
    export = export_stack_pose_model if kind == "stack-pose" else export_model
    out = export(source, args.output_model, provenance=provenance, overwrite=args.overwrite)
    step = (config.get("training") or {}).get("step") if kind == "slice-pose" else None
    card = _CARD.format(
        kind=kind.capitalize(),
        source=source,
        step="" if step is None else f", step {step}",
        data=args.data,
        command=provenance["training_command"],
    )
    atomic_write_text(out / "README.md", card, overwrite=True)
    size = sum(f.stat().st_size for f in Path(out).iterdir() if f.is_file())
    print(f"wrote {out} ({size / 1e6:.2f} MB): {kind} model from {source}")
    return 0
