r"""Train the shipped brain-mask model (svr.models.brain_mask) on simulated scenes only.

Each network is one process (one core each; run the two stages side by side), then ``assemble``
puts the two into one model folder; the defaults reproduce the shipped model (about 12 min of
simulation and 30 min of training per network on one core):

    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py localiser --out runs/brainmask &
    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py segmenter --out runs/brainmask &
    wait
    python benchmarks/train_brain_masker.py assemble --out runs/brainmask \\
        --model models/pretrained/brain_mask --overwrite

A stage caches its simulated examples (``OUT/STAGE/examples.pt``) and resumes from its newest
checkpoint, so an interrupted run goes on where it stopped. The atlas (``--atlas``) supplies the
brains; no real scan is read.
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from dataclasses import asdict
from pathlib import Path

import torch

from svr.image import load_nifti
from svr.models.brain_mask import BrainMaskConfig, BrainMasker, save_brain_masker
from svr.models.brain_mask_train import (
    BrainMaskTrainingConfig,
    TrainingExamples,
    make_examples,
    train_network,
)
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.sampling.volume import atlas_volume_paths, load_volumes

MODEL_CARD = """\
# Shipped brain-mask model (`svr segment-stack`)

Two 2D U-Nets (`svr.models.segmentation.BrainUNet`, width 8, depth 4; float16 safetensors and a
JSON config, loaded by `svr.models.brain_mask.load_brain_masker("default")` without running
code): a localiser on 3 mm whole-slice canvases and a segmenter on 1.25 mm canvases centred on
the brain (`svr.models.brain_mask`). Masks are intracranial (the brain and the CSF around it).

**Training data.** Simulated only; no real scan was used. Brains: the 15 volumes of the
sb-fidon2021 atlas (GA 21-34, `../shared/data/atlas/sb-fidon2021`, CC0), placed in random
whole-uterus scenes (`svr.sampling.scenes.make_scene`, settings in
`svr.models.brain_mask_train.stage_data`) or alone, cut by the project's stack simulator.
{config.cases} cases per network (seed {config.seed}), {config.steps} steps of
{config.batch_size} canvases each, one CPU thread per network.

**Reproduce** (from the repository root; each stage resumes from its newest checkpoint):

    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py localiser --out {out} \\
        --cases {config.cases} --steps {config.steps} &
    OMP_NUM_THREADS=1 python benchmarks/train_brain_masker.py segmenter --out {out} \\
        --cases {config.cases} --steps {config.steps} &
    wait
    python benchmarks/train_brain_masker.py assemble --out {out} \\
        --model models/pretrained/brain_mask --overwrite

**Evaluation.** `benchmarks/bench_brain_masks.py`; figures in
`benchmarks/results/brain-masks.md`.
"""

ATLAS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "atlas" / "sb-fidon2021"


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
    parser.add_argument("--model", type=Path, help="assemble: the model folder to write")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    mask_config = BrainMaskConfig()
    config = BrainMaskTrainingConfig(cases=args.cases, steps=args.steps, seed=args.seed)

    if args.stage == "assemble":
        if args.model is None:
            parser.error("assemble needs --model")
        masker = BrainMasker(mask_config)
        provenance: dict[str, object] = {"command": " ".join(sys.argv)}
        trained = []
        for stage in ("localiser", "segmenter"):
            newest = latest_checkpoint(args.out / stage)
            if newest is None:
                parser.error(f"{args.out / stage} holds no checkpoint")
            checkpoint = load_checkpoint(newest)
            getattr(masker, stage).load_state_dict(checkpoint.state_dict)
            provenance[stage] = {"checkpoint": newest.name, "train": checkpoint.config["train"]}
            trained.append(BrainMaskTrainingConfig(**checkpoint.config["train"]))
        if trained[0] != trained[1]:
            parser.error(f"the stages were trained differently: {trained[0]} and {trained[1]}")
        save_brain_masker(masker, args.model, provenance, overwrite=args.overwrite)
        card = MODEL_CARD.format(config=trained[0], out=args.out)
        (args.model / "README.md").write_text(card)
        print(f"wrote {args.model}")
        return 0

    stage = args.stage
    folder = args.out / stage
    folder.mkdir(parents=True, exist_ok=True)
    cache = folder / "examples.pt"
    if cache.exists():
        data = torch.load(cache, weights_only=True)
        examples = TrainingExamples(data["inputs"], data["targets"])
    else:
        began = time.time()
        pairs = atlas_volume_paths(args.atlas)
        brains, _ = load_volumes(pairs)
        tissue_labels = None
        if args.label_intensities:
            tissue_labels = [
                load_nifti(v.parent / "parcellation.nii.gz").data.round().long() for v, _ in pairs
            ]
        examples = make_examples(
            brains, stage, mask_config, config, progress=True, tissue_labels=tissue_labels
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
