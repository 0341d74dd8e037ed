r"""Train the shipped brain-mask model (svr.masking) on simulated scenes only.

Each network is one process (one core each; run the two stages side by side), then ``assemble``
puts the two into one model folder. The shipped model (simulation + training: about 17 + 21 min
for the localiser, 10 + 88 min for the width-12 segmenter, on one core each):

    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py localiser --out runs/brainmask-v3 \
        --tiles --label-intensities --intensity-curves 0.5 --cases 80 --steps 3000 &
    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py segmenter --out runs/brainmask-v3 \
        --tiles --label-intensities --intensity-curves 0.5 --cases 100 --steps 5000 \
        --segmenter-width 12 &
    wait
    python benchmarks/train_brain_masker.py assemble --out runs/brainmask-v3 --tiles \
        --segmenter-width 12 --model models/pretrained/brain_mask --overwrite

Without ``--tiles`` the first recipe (one 3 mm canvas for the localiser, segmenter trained on
the brain's slices only, masks inside the skull) is trained. ``--faces``, ``--spinal-cord``,
``--partial-volume-masks`` and ``--grazing-only`` (heads with a face and eyes over a neck, heads
ending at the skull base, slice masks through the slice's thickness, the latter only on the
slices grazing the head's ends), ``--thick-skulls`` (2-5 mm grey skulls inside the masks, thin
scalps) and ``--segmenter-context 1`` (a 2.5D segmenter that sees each
slice with one neighbour on either side; give it to ``assemble`` too) train the variants of
``benchmarks/results/brain-masks-variants.md``; the shipped model uses none of them. A stage
caches its simulated examples (``OUT/STAGE/examples.pt``) and resumes from its newest
checkpoint, so an interrupted run goes on where it stopped. The atlas (``--atlas``) supplies
the brains; no real scan is read.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import logging
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from svr.files import atomic_write_text
from svr.image import load_nifti
from svr.masking import BrainMaskConfig, BrainMasker, save_brain_masker
from svr.masking.train import (
    BrainMaskTrainingConfig,
    TrainingExamples,
    make_examples,
    stage_data,
    train_network,
)
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.models.segmentation import SegmentationConfig
from svr.sampling.volume import atlas_volume_paths, load_volumes

MODEL_CARD = """\
# Shipped brain-mask model (`svr segment-stack`)

Two 2D U-Nets (`svr.models.segmentation.BrainUNet`, depth 4, width 8 for the localiser and 12
for the segmenter; float16 safetensors and a JSON config, loaded by
`svr.masking.load_brain_masker("default")` without running code),
`svr.masking`: a localiser on 1.5 mm canvases of 192 mm tiled over each slice's
field of view (overlapping by half, blended), which gives the brain's in-plane centre, and a
segmenter on 1.25 mm canvases of 160 mm centred there, run on every slice. The clean-up keeps
the largest 3D component, opens it by a ball of 8 mm (cutting thin leaks into the fluid beside
the head and pieces of the body joined by narrow bridges), gives back the voxels within 3 mm of
the opened mask and fills holes slice by slice. Masks are intracranial up to the skull's outer
edge (the brain, the CSF around it and the skull's dark rim, as the manual masks of clinical
stacks are drawn).

**Training data.** Simulated only; no real scan was used. Brains: the 15 volumes of the
sb-fidon2021 atlas (GA 21-34, `../shared/data/atlas/sb-fidon2021`, CC0), placed in random
whole-uterus scenes (`svr.sampling.scenes.make_scene`, settings in
`svr.masking.train.stage_data`) or alone, cut by the project's stack simulator.
Localiser: {localiser.cases} cases, {localiser.steps} steps; segmenter: {segmenter.cases} cases,
{segmenter.steps} steps ({segmenter.batch_size} canvases a step, seed {segmenter.seed}, one CPU
thread per network; random intensity maps on a fraction {localiser.intensity_curves} /
{segmenter.intensity_curves} of the canvases).

**Reproduce** (from the repository root; each stage resumes from its newest checkpoint):

    {command}

**Evaluation.** `benchmarks/bench_brain_masks.py`; figures in
`benchmarks/results/brain-masks.md`.
"""

ATLAS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "atlas" / "sb-fidon2021"
# The commands behind the shipped model (written into its model card).
REPRODUCE = """\
OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py localiser --out runs/brainmask-v3 \\
        --tiles --label-intensities --intensity-curves 0.5 --cases 80 --steps 3000 &
    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py segmenter --out runs/brainmask-v3 \\
        --tiles --label-intensities --intensity-curves 0.5 --cases 100 --steps 5000 \\
        --segmenter-width 12 &
    wait
    python benchmarks/train_brain_masker.py assemble --out runs/brainmask-v3 --tiles \\
        --segmenter-width 12 --model models/pretrained/brain_mask --overwrite"""
# --tiles: the localiser on 1.5 mm tiles of 192 mm covering the field of view, every slice
# segmented, the mask opened by an 8 mm ball and regrown by 3 mm (chosen on held-out simulated
# stacks: benchmarks/results/brain-masks-variants.md)
TILED = {
    "localiser_mm": 1.5,
    "localiser_size": 128,
    "localiser_tiles": True,
    "slice_margin": None,
    "opening_mm": 8.0,
    "regrow_mm": 3.0,
}

# The mask-config fields a stage's training depends on (the rest only matter at inference).
STAGE_FIELDS = {
    "localiser": ("localiser_mm", "localiser_size", "localiser", "localiser_tiles"),
    "segmenter": ("segmenter_mm", "segmenter_size", "segmenter", "localiser_tiles"),
}
SETTINGS = "settings.json"  # in each stage folder: what its examples and training depend on


def stage_settings(
    stage: str,
    mask_config: BrainMaskConfig,
    config: BrainMaskTrainingConfig,
    args: argparse.Namespace,
) -> dict[str, object]:
    """Everything a stage's examples and weights depend on (a resumed run must match it)."""
    mask = mask_config.to_dict()
    return {
        "mask_config": {k: mask[k] for k in STAGE_FIELDS[stage]},
        "train": asdict(config),
        "label_intensities": args.label_intensities,
        "segment_all_slices": args.segment_all_slices,
        "tight_heads": args.tight_heads,
        "faces": args.faces,
        "partial_volume_masks": args.partial_volume_masks,
        "spinal_cord": args.spinal_cord,
        "grazing_only": args.grazing_only,
        "thick_skulls": args.thick_skulls,
    }


def recorded_settings(path: Path) -> dict[str, Any]:
    """A stage's recorded settings, with the defaults of settings added since it was written."""
    # (runs recorded before a setting existed had its default)
    settings: dict[str, Any] = {
        "tight_heads": False,
        "faces": False,
        "partial_volume_masks": False,
        "spinal_cord": False,
        "grazing_only": False,
        "thick_skulls": False,
        **json.loads(path.read_text()),
    }
    mask = settings["mask_config"]
    for name in ("localiser", "segmenter"):
        if name in mask:  # (e.g. in_channels, added with 2.5D segmenters)
            mask[name] = asdict(SegmentationConfig(**mask[name]))
    return settings


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["localiser", "segmenter", "assemble"])
    parser.add_argument("--out", type=Path, required=True, help="run folder")
    parser.add_argument("--atlas", type=Path, default=ATLAS, help="atlas folder (GA*/srr.nii.gz)")
    parser.add_argument("--cases", type=int, default=BrainMaskTrainingConfig.cases)
    parser.add_argument("--steps", type=int, default=BrainMaskTrainingConfig.steps)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--label-intensities",
        action="store_true",
        help="give half of the scenes' brains a random intensity per parcellation label",
    )
    parser.add_argument(
        "--tiles",
        action="store_true",
        help="localiser on 1.5 mm tiles over the field of view (BrainMaskConfig.localiser_tiles)",
    )
    parser.add_argument(
        "--intensity-curves",
        type=float,
        default=BrainMaskTrainingConfig.intensity_curves,
        help="fraction of training canvases given a random increasing intensity map",
    )
    parser.add_argument(
        "--segment-all-slices",
        action="store_true",
        help="segmenter: canvases from every slice, not only the brain's (StageData field)",
    )
    parser.add_argument(
        "--tight-heads",
        action="store_true",
        help="scenes with narrower CSF, fainter thinner skulls and scalps (stage_data)",
    )
    parser.add_argument(
        "--faces",
        action="store_true",
        help="scenes whose heads have a face and eyes and whose bodies hang from a neck",
    )
    parser.add_argument(
        "--partial-volume-masks",
        action="store_true",
        help="slice masks wherever a fifth of the slice's profile is brain (stage_data)",
    )
    parser.add_argument(
        "--grazing-only",
        action="store_true",
        help="with --partial-volume-masks: only on slices grazing the head's ends (stage_data)",
    )
    parser.add_argument(
        "--thick-skulls",
        action="store_true",
        help="scenes with 2-5 mm grey skulls (in the segmenter's masks) and thin scalps",
    )
    parser.add_argument(
        "--spinal-cord",
        action="store_true",
        help="heads end at the skull base; the brainstem below is the cord (SceneConfig)",
    )
    parser.add_argument(
        "--segmenter-width",
        type=int,
        default=BrainMaskConfig().segmenter.width,
        help="channels of the segmenter's first level (give the same to assemble)",
    )
    parser.add_argument(
        "--segmenter-context",
        type=int,
        default=BrainMaskConfig().segmenter_context,
        help="neighbouring slices on either side the segmenter sees (0: 2D; give the same to "
        "assemble)",
    )
    parser.add_argument("--model", type=Path, help="assemble: the model folder to write")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    mask_config = BrainMaskConfig(**(TILED if args.tiles else {}))
    mask_config = dataclasses.replace(
        mask_config,
        segmenter=dataclasses.replace(
            mask_config.segmenter,
            width=args.segmenter_width,
            in_channels=1 + 2 * args.segmenter_context,
        ),
    )
    config = BrainMaskTrainingConfig(
        cases=args.cases,
        steps=args.steps,
        seed=args.seed,
        intensity_curves=args.intensity_curves,
    )

    if args.stage == "assemble":
        if args.model is None:
            parser.error("assemble needs --model")
        masker = BrainMasker(mask_config)
        provenance: dict[str, object] = {"command": " ".join(sys.argv)}
        trained = {}
        for stage in ("localiser", "segmenter"):
            newest = latest_checkpoint(args.out / stage)
            if newest is None:
                parser.error(f"{args.out / stage} holds no checkpoint")
            recorded = args.out / stage / SETTINGS
            if recorded.exists():
                wanted = stage_settings(stage, mask_config, config, args)["mask_config"]
                if recorded_settings(recorded)["mask_config"] != wanted:
                    parser.error(f"{recorded}: trained for another mask config (--tiles?)")
            checkpoint = load_checkpoint(newest)
            getattr(masker, stage).load_state_dict(checkpoint.state_dict)
            provenance[stage] = {"checkpoint": newest.name, "train": checkpoint.config["train"]}
            trained[stage] = BrainMaskTrainingConfig(**checkpoint.config["train"])
        save_brain_masker(masker, args.model, provenance, overwrite=args.overwrite)
        card = MODEL_CARD.format(
            localiser=trained["localiser"], segmenter=trained["segmenter"], command=REPRODUCE
        )
        atomic_write_text(args.model / "README.md", card, overwrite=True)
        print(f"wrote {args.model}")
        return 0

    stage = args.stage
    folder = args.out / stage
    folder.mkdir(parents=True, exist_ok=True)
    settings = stage_settings(stage, mask_config, config, args)
    recorded = folder / SETTINGS
    if args.grazing_only and not args.partial_volume_masks:
        parser.error("--grazing-only needs --partial-volume-masks")
    if args.thick_skulls and args.tight_heads:
        parser.error("--thick-skulls and --tight-heads exclude each other")
    if recorded.exists() and recorded_settings(recorded) != settings:
        parser.error(
            f"{recorded}: this run folder was started with other settings "
            f"({json.loads(recorded.read_text())}); give another --out"
        )
    atomic_write_text(recorded, json.dumps(settings, indent=1), overwrite=True)
    cache = folder / "examples.pt"
    if cache.exists():
        cached = torch.load(cache, weights_only=True)
        examples = TrainingExamples(cached["inputs"], cached["targets"])
    else:
        began = time.time()
        pairs = atlas_volume_paths(args.atlas)
        brains, _ = load_volumes(pairs)
        tissue_labels = None
        if args.label_intensities:
            tissue_labels = [
                load_nifti(v.parent / "parcellation.nii.gz").data.round().long() for v, _ in pairs
            ]
        data = stage_data(
            stage,
            mask_config.localiser_tiles,
            args.tight_heads,
            faces=args.faces,
            partial_volume=args.partial_volume_masks,
            spinal_cord=args.spinal_cord,
            grazing_only=args.grazing_only,
            thick_skulls=args.thick_skulls,
        )
        if args.segment_all_slices:
            data = dataclasses.replace(data, segment_all_slices=True)
        examples = make_examples(
            brains, stage, mask_config, config, data, progress=True, tissue_labels=tissue_labels
        )
        torch.save({"inputs": examples.inputs, "targets": examples.targets}, cache)
        logging.info(
            "%d %s examples (brain %.2f %% of pixels) in %.0f s",
            examples.inputs.shape[0],
            stage,
            100 * float(examples.targets.float().mean()),
            time.time() - began,
        )
    net_config = getattr(mask_config, stage)
    train_network(examples, net_config, config, folder, progress=True)
    logging.info("done: %s", asdict(config))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
