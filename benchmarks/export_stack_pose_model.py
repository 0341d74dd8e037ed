"""Write the shipped stack-pose model (``models/pretrained/stack_pose``) from a training run.

Run from the repository root::

    python benchmarks/export_stack_pose_model.py --checkpoint RUN_OR_STEP_FOLDER \
        --out models/pretrained/stack_pose [--overwrite]

The model folder gets the float16 weights, a config with the provenance (the training command and
data, read from the checkpoint) and a ``README.md`` model card pointing to the evaluation.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from svr.models.checkpoint import CheckpointError, load_checkpoint, resolve_model_path
from svr.models.pretrained.export import export_stack_pose_model

CARD = """# Shipped stack-pose model (`--registration cnn --model stack-pose`)

A small 3D CNN (`svr.models.stack_pose.StackPoseNet`, head `{head}`, width {width}, blocks of
{grid}³ voxels at {spacing:g} mm; float16 safetensors and a JSON config, loaded by
`svr.models.stack_pose.load_stack_pose_model("stack-pose")` without running code). It reads a
stack resampled in a candidate canonical frame and predicts the residual rigid transform to the
atlas frame and a score for the frame (`svr.models.stack_pose.estimate_stack_pose`: 8 hypotheses
from the brain mask's principal axes, each refined 3 times, the best-scored kept, then refined
again from itself and six starts turned 10 degrees about the canonical axes, the robust mean of
the seven kept).

**Training data.** Simulated only: stacks cut on the fly from 12 ages of the sb-fidon2021 atlas
(Fidon et al. 2021, CC0; GA 24, 28 and 32 held out){variants}{phantoms}, with real fetal head
motion (SVoRT's trajectories, Apache-2.0) and the artefacts listed in
`svr.models.stack_pose_train`.
Steps: {step}{phases} ({minutes}). Loss: the SE(3) geodesic loss on the stack pose, plus the
score's cross-entropy.

**Reproduce** (from the repository root; a run resumes from its newest checkpoint; ATLAS and the
trajectories as in `docs/training.md`):

{recipe}
    python benchmarks/export_stack_pose_model.py --checkpoint RUN \\
        --out models/pretrained/stack_pose --overwrite

**Evaluation.** `benchmarks/bench_learned_stack_poses.py` (per-stack accuracy) and
`benchmarks/bench_reconstruct.py --registrations stack cnn --model stack-pose` (reconstruction);
figures in `benchmarks/results/learned-stack-poses.md` (the one-command recipe against the
two-run model: `benchmarks/results/learned-stack-poses-one-command.md`). Check the real scan's
output frame too (`benchmarks/bench_real_frame.py`): simulated stacks did not tell a model that
fails there.
"""


def _phantom_sentence(phantoms: object) -> str:
    """The card's words for the procedural phantoms a run trained on (none: empty)."""
    if not phantoms:
        return ""
    count = len(phantoms) if isinstance(phantoms, list) else phantoms
    return (
        f" and {count} procedural phantom brains (`svr.sampling.phantom`, seeds 1-{count}, ages "
        "spread over 22-36 weeks; seed 0, the benchmarks' phantom, never)"
    )


def _variants_sentence(variants: object) -> str:
    """The card's words for the anatomy variants a run trained on (none: empty)."""
    if not variants:
        return ""
    return (
        f", {variants} label-edited variants of each (`svr.sampling.anatomy`: ventricles shrunk, "
        "cerebellum grown, contrast re-drawn per tissue label)"
    )


def _phases_sentence(train: dict, data: dict) -> str:
    """The card's words for a two-phase run (one phase: empty)."""
    last = int(train.get("fine_tune_steps") or 0)
    if not last:
        return ""
    joined = ["the phantoms"] if data.get("phantoms") else []
    if data.get("anatomy_variants") and data.get("variants_phase") == "second":
        joined.append("the variants")
    added = f" and {' and '.join(joined)} added" if joined else ""
    fresh = train.get("fine_tune_seed")
    how = "" if fresh is None else f" as a fresh fine-tuning run (a new Adam, seed {fresh})"
    return (
        f", the last {last}{how} with the learning rate restarted at "
        f"{train.get('fine_tune_learning_rate'):g}{added}"
    )


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--out", type=Path, default=Path("models/pretrained/stack_pose"))
    parser.add_argument(
        "--minutes",
        default="one run on one CPU core",
        help="the last run's training time and machine, for the card",
    )
    parser.add_argument(
        "--recipe",
        action="append",
        default=None,
        metavar="COMMAND",
        help="a user-facing command of the recipe that made the model, in order (repeat for a "
        "fine-tuned model); default: the single-run recipe",
    )
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    try:
        source = resolve_model_path(args.checkpoint)
    except CheckpointError as err:
        parser.error(str(err))
    checkpoint = load_checkpoint(source, with_training_state=True)
    config = checkpoint.config
    assert checkpoint.training_state is not None
    step = int(checkpoint.training_state["step"])
    recipe = args.recipe or [
        "svr train-stack-pose --atlas-dir ATLAS --hold-out 24 28 32 --motion-path "
        "svort_fetal_motion_trajectories.npz --output-dir RUN"
    ]
    data = config.get("data", {})
    provenance = {
        # The run's own command names the machine's paths; the recipe names the user's.
        "training_command": recipe[0] if len(recipe) == 1 else recipe,
        "data": {
            "atlas": "sb-fidon2021 (Fidon et al. 2021, zenodo.org/record/5524312, CC0 1.0)",
            "hold_out_weeks": [24, 28, 32],
            "motion": "SVoRT fetal head-motion trajectories (Apache-2.0)",
            **({"phantoms": data["phantoms"]} if data.get("phantoms") else {}),
            **(
                {
                    "anatomy_variants": data["anatomy_variants"],
                    "variants_phase": data.get("variants_phase", "all"),
                }
                if data.get("anatomy_variants")
                else {}
            ),
        },
        "step": step,
        "train": config.get("train"),
    }
    out = export_stack_pose_model(source, args.out, provenance=provenance, overwrite=args.overwrite)
    model = config["model"]
    card = CARD.format(
        head=model["head"],
        width=model["width"],
        grid=model["grid_size"],
        spacing=model["grid_spacing_mm"],
        step=step,
        phases=_phases_sentence(config.get("train") or {}, data),
        minutes=args.minutes,
        phantoms=_phantom_sentence(data.get("phantoms")),
        variants=_variants_sentence(data.get("anatomy_variants")),
        recipe="\n".join(f"    {line}" for line in recipe),
    )
    (out / "README.md").write_text(card, encoding="utf-8")
    size = sum(f.stat().st_size for f in out.iterdir())
    print(f"wrote {out} ({size / 1e6:.2f} MB) from {source} (step {step})")
    print(json.dumps(provenance, indent=1)[:400])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
