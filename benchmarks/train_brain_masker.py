r"""Train the shipped brain-mask model (svr.models.brain_mask) on simulated scenes only.

Each network is one process (one core each; run the two stages side by side), then ``assemble``
puts the two into one model folder:

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

from svr.models.brain_mask import BrainMaskConfig, BrainMasker, save_brain_masker
from svr.models.brain_mask_train import (
    BrainMaskTrainingConfig,
    TrainingExamples,
    make_examples,
    train_network,
)
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.sampling.volume import atlas_volume_paths, load_volumes

ATLAS = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "atlas" / "sb-fidon2021"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("stage", choices=["localiser", "segmenter", "assemble"])
    parser.add_argument("--out", type=Path, required=True, help="run folder")
    parser.add_argument("--atlas", type=Path, default=ATLAS, help="atlas folder (GA*/srr.nii.gz)")
    parser.add_argument("--cases", type=int, default=BrainMaskTrainingConfig.cases)
    parser.add_argument("--steps", type=int, default=BrainMaskTrainingConfig.steps)
    parser.add_argument("--seed", type=int, default=0)
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
        for stage in ("localiser", "segmenter"):
            newest = latest_checkpoint(args.out / stage)
            if newest is None:
                parser.error(f"{args.out / stage} holds no checkpoint")
            checkpoint = load_checkpoint(newest)
            getattr(masker, stage).load_state_dict(checkpoint.state_dict)
            provenance[stage] = {"checkpoint": newest.name, "train": checkpoint.config["train"]}
        save_brain_masker(masker, args.model, provenance, overwrite=args.overwrite)
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
        brains, _ = load_volumes(atlas_volume_paths(args.atlas))
        examples = make_examples(brains, stage, mask_config, config, progress=True)
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
