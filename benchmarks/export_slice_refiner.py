"""Write the shipped slice refiner (``models/pretrained/slice_refiner``) from two training runs.

Run from the repository root::

    python benchmarks/export_slice_refiner.py --wide RUN_30 --fine RUN_10 \
        --out models/pretrained/slice_refiner [--overwrite]

``RUN_30`` and ``RUN_10`` are checkpoint folders (or run folders: their newest step) of
``benchmarks/experiments/calibrate_slice_refiner.py --out`` with ``--max-turn 30`` and
``--max-turn 10``. Each stage becomes a float16 model folder (``wide/``, ``fine/``) with its
provenance; ``README.md`` is the model card.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from svr.models.checkpoint import resolve_model_path
from svr.models.pretrained import SLICE_REFINER_STAGES
from svr.models.pretrained.export import export_slice_refiner

ATLAS_DATA = (
    "Simulated only: packets of slices cut on the fly from 11 ages of the sb-fidon2021 atlas "
    "(Fidon et al. 2021, CC0; GA 21-34 but the bench cases' 24, 28 and 32), with a random walk "
    "of head motion per packet; validated on the Wu 2021 atlas (GA 24, 28, 32), never trained on."
)

COMMAND = (
    "cd benchmarks/experiments && python calibrate_slice_refiner.py --fidon ATLAS --crl CRL "
    "--wu WU --train-on fidon --head coords --max-turn {turn} --pure-rotation --shift-mm 1 "
    "--steps 8500 --minutes 40 --out RUN_{turn}"
)

CARD = """# Shipped slice refiner (`--registration cnn` with an atlas)

Two stages of a small 2D CNN (`svr.models.slice_refiner.SliceRefinerNet`, head `coords`: per
cell of the slice, where its content lies, then a weighted rigid fit), float16 safetensors and a
JSON config each, loaded by `svr.models.slice_refiner.shipped_slice_refiners()` without running
code. Each sees a slice beside the atlas resampled on the slice's current plane and four parallel
planes (-12 to 12 mm) and predicts the rigid residual to the slice's true pose; the
reconstruction applies `wide` 4 times, then `fine` 3 times, and keeps a slice's new pose only
where it agrees better with the other stacks
(`svr.reconstruction.initialisation.slice_refinement`).

| stage | residuals trained on | steps | held-out validation (Wu), rotation median |
|---|---|---:|---|
{rows}

**Training data.** {data} Loss: the SE(3) geodesic loss on the residual (the default inner
product, L = 20 mm).

**Reproduce** (ATLAS, CRL and WU are atlas folders as in `docs/training.md`; CRL and WU are read
only for the validation draw):

    {command_wide}
    {command_fine}
    python benchmarks/export_slice_refiner.py --wide RUN_30 --fine RUN_10 \\
        --out models/pretrained/slice_refiner --overwrite

**Evaluation.** `benchmarks/bench_reconstruct.py` (`--registrations cnn` with `--atlas-offset 1`)
and `benchmarks/experiments/refine_in_pipeline.py`; figures in
`benchmarks/results/slice-refiner.md` and `benchmarks/results/every-slice-placed.md`.
"""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--wide", type=Path, required=True, help="the --max-turn 30 run")
    parser.add_argument("--fine", type=Path, required=True, help="the --max-turn 10 run")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--validation", nargs=2, default=["", ""], help="the card's figures")
    parser.add_argument("--overwrite", action="store_true")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    runs = dict(zip(SLICE_REFINER_STAGES, (args.wide, args.fine), strict=True))
    turns = {"wide": 30, "fine": 10}
    for (stage, run), figure in zip(runs.items(), args.validation, strict=True):
        folder = resolve_model_path(run)
        step = int(folder.name.removeprefix("step_")) if folder.name.startswith("step_") else "?"
        command = COMMAND.format(turn=turns[stage])
        provenance = {"training_command": command, "data": ATLAS_DATA, "stage": stage}
        export_slice_refiner(
            folder, args.out / stage, provenance=provenance, overwrite=args.overwrite
        )
        rows.append(
            f"| `{stage}` | rotations up to {turns[stage]} deg, 1 mm shifts | {step} | {figure} |"
        )
    card = CARD.format(
        rows="\n".join(rows),
        data=ATLAS_DATA,
        command_wide=COMMAND.format(turn=30),
        command_fine=COMMAND.format(turn=10),
    )
    (args.out / "README.md").write_text(card, encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
