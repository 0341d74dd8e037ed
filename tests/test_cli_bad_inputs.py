"""Every ``svr`` subcommand against every applicable bad input: a clean, one-line refusal.

Policy (the same for every subcommand, run in-process through :func:`svr.cli.main`):

* A bad file, value or output path found by the subcommand exits with status 1 and prints exactly
  one line on stderr, ``svr COMMAND: error: ...``, which names the file or option and the
  problem; no traceback. With ``--verbose`` the same error also prints its traceback, and the
  last line of stderr is the same one-line message.
* A value that argparse refuses (its type or choices) exits with status 2: argparse's usage lines
  and one ``svr COMMAND: error: argument --OPTION: ...`` line, which names the option.
* Nothing is written: every existing file under the output folder is byte-identical afterwards,
  no new file or folder appears there or among the inputs, and a pickle payload in a checkpoint
  or motion file never runs (its marker file never appears).

Error cases run with ``-q``: progress bars and info logging are for successful runs.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import os
import pathlib
import pickle
import shutil
import struct
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import torch
from synthetic import ellipsoid_brain

import svr.apps.demo as recon_demo
import svr.apps.tissue as tissue_app
import svr.files
import svr.image
import svr.masking as brain_mask
import svr.masking.recipe as mask_recipe
import svr.reconstruction.pipeline as pipeline
from svr.cli import SUBCOMMANDS, main
from svr.image import save_nifti
from svr.masking import BrainMaskConfig, BrainMasker, save_brain_masker
from svr.models.backbones import BackboneConfig
from svr.models.checkpoint import (
    CHECKPOINT_CONFIG,
    CHECKPOINT_WEIGHTS,
    TRAINING_STATE,
    checkpoint_name,
    save_checkpoint,
)
from svr.models.network import ModelConfig, build_model, checkpoint_model_config
from svr.models.segmentation import SegmentationConfig

# --- the pickle payload: unpickling it creates a marker file -------------------------------------


class Payload:
    """Unpickling this creates ``marker`` (an ordinary unpickler executes ``__reduce__``)."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self):
        return open, (str(self.marker), "w")


# --- tiny inputs ---------------------------------------------------------------------------------

STACK_SHAPE = (16, 16, 6)
STACK_AFFINE = np.diag([2.0, 2.0, 4.0, 1.0])
STACK_AFFINE[:3, 3] = (-15.0, -15.0, -10.0)


def _nifti(data: np.ndarray, affine: np.ndarray = STACK_AFFINE) -> bytes:
    """Uncompressed NIfTI-1 bytes of a float32 image (sform and qform set)."""
    return nib.Nifti1Image(np.asarray(data, dtype=np.float32), affine).to_bytes()


def _patch(raw: bytes, fmt: str, offset: int, *values) -> bytes:
    out = bytearray(raw)
    struct.pack_into(fmt, out, offset, *values)
    return bytes(out)


def _write(path: Path, raw: bytes) -> str:
    path.write_bytes(gzip.compress(raw, mtime=0) if path.name.endswith(".gz") else raw)
    return str(path)


def _with_sform(raw: bytes, affine: np.ndarray) -> bytes:
    """The image with qform_code 0 and this (possibly singular or sheared) sform."""
    raw = _patch(raw, "<hh", 252, 0, 2)
    for row in range(3):
        raw = _patch(raw, "<4f", 280 + 16 * row, *affine[row])
    return raw


def _rewrite_hash(folder: Path, key: str, file: Path) -> None:
    config = json.loads((folder / CHECKPOINT_CONFIG).read_text())
    config["checkpoint"][key] = hashlib.sha256(file.read_bytes()).hexdigest()
    (folder / CHECKPOINT_CONFIG).write_text(json.dumps(config))


@pytest.fixture(scope="module")
def env(tmp_path_factory) -> dict[str, str]:
    """Every input file (good and bad) of the sweep, by name; ``root`` is their folder."""
    root = tmp_path_factory.mktemp("inputs")
    f: dict[str, str] = {"root": str(root), "marker": str(root / "payload_ran")}

    # Good inputs: a 36 mm brain volume and a thick-slice stack, with masks.
    volume, mask = ellipsoid_brain(12, 3.0, (12.0, 14.0, 11.0), seed=1, origin_mm=(-16.5,) * 3)
    f["brain"] = str(save_nifti(volume, root / "brain.nii.gz"))
    f["mask"] = str(save_nifti(mask, root / "mask.nii.gz"))
    rng = np.random.default_rng(0)
    i, j, k = np.indices(STACK_SHAPE)
    inside = ((i - 7.5) / 6) ** 2 + ((j - 7.5) / 5) ** 2 + ((k - 2.5) / 2.6) ** 2 < 1
    stack = (inside * (1 + rng.random(STACK_SHAPE))).astype(np.float32)
    f["stack"] = _write(root / "stack.nii.gz", _nifti(stack))
    f["stack_mask"] = _write(root / "stack_mask.nii.gz", _nifti(inside))
    tiny = BrainMaskConfig(
        localiser_size=16,
        segmenter_size=16,
        localiser=SegmentationConfig(2, 1),
        segmenter=SegmentationConfig(2, 1),
    )
    f["masker"] = str(save_brain_masker(BrainMasker(tiny), root / "masker"))

    # Bad NIfTI files: any image slot.
    good = _nifti(stack)
    f["missing"] = str(root / "missing.nii.gz")
    (root / "directory.nii.gz").mkdir()
    f["directory"] = str(root / "directory.nii.gz")
    f["unreadable"] = _write(root / "unreadable.nii.gz", good)
    f["not_nifti"] = _write(root / "not_nifti.nii.gz", b"this is not a NIfTI file\n" * 40)
    compressed = gzip.compress(good, mtime=0)
    (root / "truncated.nii.gz").write_bytes(compressed[: len(compressed) // 2])
    f["truncated"] = str(root / "truncated.nii.gz")
    flipped = bytearray(compressed)
    for n in range(40, len(flipped) - 16, 7):
        flipped[n] ^= 0x5A
    (root / "corrupt_gz.nii.gz").write_bytes(bytes(flipped))
    f["corrupt_gz"] = str(root / "corrupt_gz.nii.gz")
    f["truncated_nii"] = _write(root / "truncated_nii.nii", good[: len(good) // 2])
    f["bad_header"] = _write(root / "bad_header.nii.gz", _patch(good, "<h", 70, 999))  # datatype
    rgb = np.zeros(STACK_SHAPE, dtype=[("R", "u1"), ("G", "u1"), ("B", "u1")])
    f["rgb"] = _write(root / "rgb.nii.gz", nib.Nifti1Image(rgb, STACK_AFFINE).to_bytes())
    cplx = (stack + 1j * stack).astype(np.complex64)
    f["complex"] = _write(root / "complex.nii.gz", nib.Nifti1Image(cplx, STACK_AFFINE).to_bytes())
    f["two_d"] = _write(root / "two_d.nii.gz", _nifti(stack[:, :, 0]))
    f["four_d"] = _write(root / "four_d.nii.gz", _nifti(np.stack([stack, stack], axis=-1)))
    nan, inf = stack.copy(), stack.copy()
    nan[3, 4, 2] = np.nan
    inf[5, 5, 1] = -np.inf
    f["nan"] = _write(root / "nan.nii.gz", _nifti(nan))
    f["inf"] = _write(root / "inf.nii.gz", _nifti(inf))
    f["zero_dim"] = _write(root / "zero_dim.nii.gz", _patch(good, "<h", 42, 0))  # dim[1] = 0
    f["singular"] = _write(
        root / "singular.nii.gz", _with_sform(good, np.diag([2.0, 2.0, 0.0, 1.0]))
    )
    sheared = STACK_AFFINE.copy()
    sheared[0, 1] = 1.0  # in-plane axes at 63 degrees: the slices are not rectangles
    f["sheared"] = _write(root / "sheared.nii.gz", _with_sform(good, sheared))
    shutil.copy(f["stack"], root / "wrong_suffix.mgz")
    f["wrong_suffix"] = str(root / "wrong_suffix.mgz")

    # Masks that do not fit their image.
    far = STACK_AFFINE.copy()
    far[:3, 3] += 1000.0
    f["far_stack_mask"] = _write(root / "far_stack_mask.nii.gz", _nifti(inside, far))
    f["empty_stack_mask"] = _write(root / "empty_stack_mask.nii.gz", _nifti(0 * inside))
    moved = Path(save_nifti(mask, root / "moved_mask.nii.gz"))
    shifted = mask.affine.clone()
    shifted[:3, 3] += 50.0
    save_nifti(type(mask)(mask.data, shifted), moved, overwrite=True)
    f["moved_mask"] = str(moved)
    f["small_mask"] = str(save_nifti(type(mask)(mask.data[:10], mask.affine), root / "small.nii"))
    f["empty_mask"] = str(
        save_nifti(type(mask)(0 * mask.data, mask.affine), root / "empty_mask.nii.gz")
    )

    # Slice folders for predict --input-slices.
    (root / "no_slices").mkdir()
    f["no_slices"] = str(root / "no_slices")
    (root / "thick_slices").mkdir()
    _write(root / "thick_slices" / "0.nii.gz", good)
    f["thick_slices"] = str(root / "thick_slices")
    (root / "bad_slices").mkdir()
    _write(root / "bad_slices" / "0.nii.gz", b"not a slice\n" * 20)
    f["bad_slices"] = str(root / "bad_slices")

    # Checkpoints: a tiny valid model and broken copies of it.
    config = ModelConfig(
        backbone=BackboneConfig(width=8, depth=1), input_size=(32, 32), spacing_mm=2.0
    )
    torch.manual_seed(0)
    weights = build_model(config).state_dict()
    model = save_checkpoint(root / "model", weights, checkpoint_model_config(config))
    f["model"] = str(model)
    marker = Path(f["marker"])

    def broken(name: str) -> Path:
        folder = root / name
        shutil.copytree(model, folder)
        return folder

    f["ckpt_missing"] = str(root / "no_such_model")
    f["ckpt_empty"] = str(root / "empty_model")
    (root / "empty_model").mkdir()
    payload = pickle.dumps({"backbone.stem.0.weight": Payload(marker)})
    (root / "model.pt").write_bytes(payload)
    f["ckpt_pickle_file"] = str(root / "model.pt")
    folder = broken("pickle_weights")  # the weights replaced by a pickle, hash rewritten to match
    (folder / CHECKPOINT_WEIGHTS).write_bytes(payload)
    _rewrite_hash(folder, "weights_sha256", folder / CHECKPOINT_WEIGHTS)
    f["ckpt_pickle_weights"] = str(folder)
    folder = broken("pth_weights")  # a torch.save'd pickle beside the config, no safetensors
    (folder / CHECKPOINT_WEIGHTS).unlink()
    torch.save({"w": Payload(marker)}, folder / "model.pth")
    f["ckpt_pth_only"] = str(folder)
    folder = broken("truncated_weights")
    data = (folder / CHECKPOINT_WEIGHTS).read_bytes()
    (folder / CHECKPOINT_WEIGHTS).write_bytes(data[: len(data) // 2])
    _rewrite_hash(folder, "weights_sha256", folder / CHECKPOINT_WEIGHTS)
    f["ckpt_truncated"] = str(folder)
    folder = broken("stale_hash")
    (folder / CHECKPOINT_WEIGHTS).write_bytes(data[: len(data) // 2])
    f["ckpt_stale_hash"] = str(folder)
    folder = broken("bad_json")
    text = (folder / CHECKPOINT_CONFIG).read_text()
    (folder / CHECKPOINT_CONFIG).write_text(text[: len(text) // 2])
    f["ckpt_bad_json"] = str(folder)
    folder = broken("no_model_section")
    config_dict = json.loads((folder / CHECKPOINT_CONFIG).read_text())
    del config_dict["model"]
    (folder / CHECKPOINT_CONFIG).write_text(json.dumps(config_dict))
    f["ckpt_no_model"] = str(folder)
    f["ckpt_unreadable"] = str(broken("unreadable_model"))

    # Training runs to resume: one whose training state is a pickle payload (hash rewritten).
    run = root / "run_pickle_state" / "checkpoints"
    run.mkdir(parents=True)
    step = save_checkpoint(
        run / checkpoint_name(1),
        weights,
        checkpoint_model_config(config),
        training_state={"step": 1},
    )
    torch.save({"step": 1, "optimizer": Payload(marker)}, step / TRAINING_STATE)
    _rewrite_hash(step, "training_state_sha256", step / TRAINING_STATE)
    f["run_pickle_state"] = str(root / "run_pickle_state")
    f["good_step"] = str(
        save_checkpoint(
            root / "good_step",
            weights,
            checkpoint_model_config(config),
            training_state={"step": 1},
        )
    )

    # Motion trajectories for simulate --motion trajectories.
    f["motion_missing"] = str(root / "no_motion.npz")
    f["motion_junk"] = _write(root / "motion_junk.npz", b"not an npz\n" * 10)
    np.savez(root / "motion_pickle.npz", rot_000_x=np.array([Payload(marker)], dtype=object))
    f["motion_pickle"] = str(root / "motion_pickle.npz")

    # Atlas folders for --atlas-dir.
    (root / "atlas_empty").mkdir()
    f["atlas_empty"] = str(root / "atlas_empty")
    for name, srr in (("atlas_bad_name", "GAxx"), ("atlas_bad_srr", "GA28")):
        (root / name / srr).mkdir(parents=True)
        shutil.copy(
            f["not_nifti"] if name == "atlas_bad_srr" else f["brain"],
            root / name / srr / "srr.nii.gz",
        )
        shutil.copy(f["mask"], root / name / srr / "mask.nii.gz")
        f[name] = str(root / name)
    (root / "atlas_good" / "GA30").mkdir(parents=True)
    shutil.copy(f["brain"], root / "atlas_good" / "GA30" / "srr.nii.gz")
    shutil.copy(f["mask"], root / "atlas_good" / "GA30" / "mask.nii.gz")
    f["atlas_good"] = str(root / "atlas_good")
    # ... and one with tissue labels (svr segment-volume): the brain's mask as white matter
    shutil.copytree(root / "atlas_good", root / "atlas_labels")
    shutil.copy(f["mask"], root / "atlas_labels" / "GA30" / "parcellation.nii.gz")
    f["atlas_labels"] = str(root / "atlas_labels")
    # A BIDS dataset of one participant (svr bids) and its masks as a derivatives folder.
    for name in ("bids", "bids_masks"):
        (root / name / "sub-01" / "anat").mkdir(parents=True)
        (root / name / "dataset_description.json").write_text(
            '{"Name": "t", "BIDSVersion": "1.9.0"}'
        )
        f[name] = str(root / name)
    anat = root / "bids" / "sub-01" / "anat"
    shutil.copy(f["stack"], anat / "sub-01_run-1_T2w.nii.gz")
    (anat / "sub-01_run-1_T2w.json").write_text('{"SliceThickness": 4}')
    shutil.copy(
        f["stack_mask"],
        root / "bids_masks" / "sub-01" / "anat" / "sub-01_run-1_desc-brain_mask.nii.gz",
    )
    return f


# --- the cases -----------------------------------------------------------------------------------

BASE = {
    "simulate": "simulate --output-dir {out}/case --input-volume {brain} --input-mask {mask} "
    "--num-stacks 1 --thickness 6 --in-plane-resolution 4 --motion none --device cpu",
    "sample": "sample --input-volume {brain} --input-mask {mask} --num-slices 2 --size 8 "
    "--output-preview {out}/preview.png --output-dataset {out}/dataset --device cpu",
    "train": "train --output-dir {out}/run --input-volumes {brain} --input-masks {mask} "
    "--steps 1 --size 32 --spacing 2 --width 8 --depth 1 --batch-size 2 --checkpoint-every 1 "
    "--device cpu",
    "train-stack-pose": "train-stack-pose --output-dir {out}/run --atlas-dir {atlas_good} "
    "--steps 1 --fine-tune-steps 0 --phantoms 0 --width 4 --checkpoint-every 1 "
    "--volume-downsample 4 --device cpu",
    # (its training is replaced by a sentinel: inputs and outputs are checked first)
    "train-brain-mask": "train-brain-mask --output-dir {out}/run --atlas-dir {atlas_good} "
    "--output-model {out}/mask-model --cases 1 --steps 1 --device cpu",
    "export-model": "export-model --checkpoint {model} --output-model {out}/exported "
    "--data synthetic --training-command train --device cpu",
    "predict": "predict --model {model} --input-stacks {stack} --stack-masks {stack_mask} "
    "--output-poses {out}/poses.csv --device cpu",
    "evaluate": "evaluate --checkpoints {model} --input-volumes {brain} --input-masks {mask} "
    "--num-slices 2 --output-dir {out}/report --device cpu",
    "register": "register --input-stacks {stack} --stack-masks {stack_mask} --thicknesses 4 "
    "--iterations 1 --sr-iterations 1 --output-resolution 4 --output-transforms {out}/t.csv "
    "--device cpu",
    "reconstruct": "reconstruct --input-stacks {stack} --stack-masks {stack_mask} --thicknesses 4 "
    "--iterations 1 --sr-iterations 1 --output-resolution 4 --output-volume {out}/srr.nii.gz "
    "--device cpu",
    # the whole-toolkit demo (its simulation is replaced by a sentinel: inputs are checked first)
    "demo": "demo --quick --input-volume {brain} --input-mask {mask} --registration cnn "
    "--model {model} --output-dir {out}/demo --device cpu",
    "demo-loss": "demo --loss-only --num-poses 2 --steps 1 --output {out}/demo.json --device cpu",
    "segment-stack": "segment-stack --input-stacks {stack} --output-stack-masks {out}/mask.nii.gz "
    "--mask-model {masker} --output-qa {out}/masks.png --device cpu",
    # labels of a volume (the segmentation is replaced by a sentinel)
    "segment-volume": "segment-volume --input-volume {brain} --atlas-dir {atlas_labels} "
    "--gestational-age 30 --output-labels {out}/dseg.nii.gz --output-report {out}/report.html",
    # positional BIDS_DIR OUTPUT_DIR participant (the reconstruction is replaced by a sentinel)
    "bids": "bids {bids} {out}/derivatives participant --masks-dir {bids_masks} --iterations 1 "
    "--sr-iterations 1 --output-resolution 4 --device cpu",
}

# command -> the options that take its image and its mask
IMAGE_SLOTS = {
    "simulate": ("--input-volume", "--input-mask"),
    "sample": ("--input-volume", "--input-mask"),
    "train": ("--input-volumes", "--input-masks"),
    "predict": ("--input-stacks", "--stack-masks"),
    "evaluate": ("--input-volumes", "--input-masks"),
    "register": ("--input-stacks", "--stack-masks"),
    "reconstruct": ("--input-stacks", "--stack-masks"),
    "demo": ("--input-volume", "--input-mask"),
}

# bad file -> what the message says about it (besides the file's path)
BAD_FILES = {
    "missing": "no such file",
    "directory": "not a file",
    "unreadable": "permission denied",
    "not_nifti": "cannot read as NIfTI",
    "truncated": "cannot read as NIfTI",
    "truncated_nii": "cannot read as NIfTI",
    "corrupt_gz": "cannot read as NIfTI",
    "bad_header": "cannot read as NIfTI",
    "rgb": "data type",
    "complex": "data type",
    "two_d": "expected a 3D image, got 2D",
    "four_d": "expected a 3D image, got 4D",
    "nan": "1 voxels are NaN or Inf",
    "inf": "1 voxels are NaN or Inf",
    "zero_dim": "image is empty",
    "singular": "singular",
    "wrong_suffix": "not a NIfTI file name",
}

CHECKPOINT_OPTIONS = {
    "predict": ["--model"],
    "evaluate": ["--checkpoints"],
    "register": ["--registration", "cnn", "--model"],
    "reconstruct": ["--registration", "cnn", "--model"],
    "demo": ["--model"],
}

# bad checkpoint -> (message for predict/register/reconstruct, message for evaluate)
BAD_CHECKPOINTS = {
    "ckpt_missing": ("checkpoint folder does not exist", "checkpoint folder does not exist"),
    "ckpt_empty": ("missing config.json", "missing config.json"),
    "ckpt_pickle_file": ("not a checkpoint folder (a file)", "not a checkpoint folder (a file)"),
    "ckpt_pickle_weights": ("corrupted safetensors file", "corrupted safetensors file"),
    "ckpt_pth_only": ("missing model.safetensors", "missing model.safetensors"),
    "ckpt_truncated": ("corrupted safetensors file", "corrupted safetensors file"),
    "ckpt_stale_hash": ("does not match its SHA-256", "does not match its SHA-256"),
    "ckpt_bad_json": ("not valid JSON", "not valid JSON"),
    "ckpt_no_model": ('no "model" section', 'no "model" section'),
    "ckpt_unreadable": ("permission denied", "permission denied"),
}

# the outputs that each command writes (left in place before an "exists" case)
EXISTING = {
    "simulate": ("case/", "--output-dir"),
    "sample": ("preview.png", "--output-preview"),
    "train": None,  # resuming is the default; see the --no-resume case
    "train-stack-pose": None,  # resuming is the default
    "train-brain-mask": ("mask-model/", "--output-model"),
    "export-model": ("exported/", "--output-model"),
    "predict": ("poses.csv", "--output-poses"),
    "evaluate": ("report/", "--output-dir"),
    "register": ("t.csv", "--output-transforms"),
    "reconstruct": ("srr.nii.gz", "--output-volume"),
    "demo": ("demo/", "--output-dir"),
    "demo-loss": ("demo.json", "--output"),
    "segment-stack": ("mask.nii.gz", "--output-stack-masks"),
    "segment-volume": ("dseg.nii.gz", "--output-labels"),
}

OUTPUT_OPTION = {
    "simulate": ("--output-dir", "case"),
    "sample": ("--output-dataset", "dataset"),
    "train": ("--output-dir", "run"),
    "train-stack-pose": ("--output-dir", "run"),
    "train-brain-mask": ("--output-model", "mask-model"),
    "export-model": ("--output-model", "exported"),
    "predict": ("--output-poses", "poses.csv"),
    "evaluate": ("--output-dir", "report"),
    "register": ("--output-transforms", "t.csv"),
    "reconstruct": ("--output-volume", "srr.nii.gz"),
    "demo": ("--output-dir", "demo"),
    "demo-loss": ("--output", "demo.json"),
    "segment-stack": ("--output-stack-masks", "mask.nii.gz"),
    "segment-volume": ("--output-labels", "dseg.nii.gz"),
}

CPU_ONLY = {"segment-volume"}
"""Commands without ``--device``: SimpleITK on the CPU (``--threads``)."""


@dataclass
class Case:
    """One bad invocation: ``command`` with ``changes`` to its base arguments."""

    id: str
    command: str  # a key of BASE
    changes: list[str]  # option followed by its values; replaces that option or is appended
    expect: list[str]  # substrings of the error line ({name} placeholders are filled in)
    code: int = 1
    setup: str | None = None  # see _setup()
    xfail: str | None = None
    drop: list[str] = field(default_factory=list)  # options removed from the base arguments


def ref(name: str) -> str:
    """The placeholder of an input file: ``{name}``, filled in by :func:`_argv`."""
    return "{" + name + "}"


def _cases() -> list[Case]:
    cases: list[Case] = []
    add = cases.append
    for command, slots in IMAGE_SLOTS.items():
        for slot_index, option in enumerate(slots):
            for bad, problem in BAD_FILES.items():
                add(
                    Case(
                        f"{command}-{option[2:]}-{bad}",
                        command,
                        [option, ref(bad)],
                        [ref(bad), problem],
                        setup="unreadable" if bad == "unreadable" else None,
                    )
                )
            if slot_index == 0 and command in ("register", "reconstruct"):
                add(
                    Case(
                        f"{command}-sheared-stack",
                        command,
                        [option, "{sheared}"],
                        ["{sheared}", "in-plane axes", "not orthogonal"],
                    )
                )
        mask_option = slots[1]
        if command in ("simulate", "sample", "train", "evaluate", "demo"):
            for bad in ("moved_mask", "small_mask"):
                add(
                    Case(
                        f"{command}-{bad}",
                        command,
                        [mask_option, ref(bad)],
                        ["{brain}", ref(bad), "grids differ"],
                    )
                )
            add(
                Case(
                    f"{command}-empty-mask",
                    command,
                    [mask_option, "{empty_mask}"],
                    ["{empty_mask}", "the mask is empty"],
                )
            )
            if command in ("train", "evaluate"):
                add(
                    Case(
                        f"{command}-mask-count",
                        command,
                        [mask_option, "{mask}", "{mask}"],
                        ["--input-volumes (1) and --input-masks (2) must pair up"],
                    )
                )
            else:
                add(
                    Case(
                        f"{command}-volume-without-mask",
                        command,
                        [],
                        ["--input-volume and --input-mask go together"],
                        drop=[mask_option],
                    )
                )
        else:
            add(
                Case(
                    f"{command}-far-mask",
                    command,
                    [mask_option, "{far_stack_mask}"],
                    ["{far_stack_mask}", "does not overlap"],
                )
            )
            add(
                Case(
                    f"{command}-empty-mask",
                    command,
                    [mask_option, "{empty_stack_mask}"],
                    ["{empty_stack_mask}", "the mask is empty"],
                )
            )
            add(
                Case(
                    f"{command}-mask-count",
                    command,
                    [mask_option, "{stack_mask}", "{stack_mask}"],
                    ["--stack-masks: got 2 masks for 1 stacks"],
                )
            )

    for bad, problem in BAD_FILES.items():
        add(
            Case(
                f"segment-stack-input-stacks-{bad}",
                "segment-stack",
                ["--input-stacks", ref(bad)],
                [ref(bad), problem],
                setup="unreadable" if bad == "unreadable" else None,
            )
        )
    add(
        Case(
            "segment-stack-count",
            "segment-stack",
            ["--input-stacks", "{stack}", "{stack}"],
            ["--output-stack-masks: got 1 paths for 2 stacks"],
        )
    )
    for option, path, message in (
        ("--output-stack-masks", "{out}/mask.mgz", "must end in .nii or .nii.gz"),
        ("--output-qa", "{out}/masks.txt", "must end in .png or .pdf"),
        ("--output-stack-masks", "{stack}", "the same path as --input-stacks"),
    ):
        add(
            Case(
                f"segment-stack-{option[2:]}-{Path(path).suffix or 'input'}",
                "segment-stack",
                [option, path],
                [f"{option} {path}: {message}"],
            )
        )
    add(
        Case(
            "segment-stack-qa-exists",
            "segment-stack",
            [],
            ["{out}/masks.png", "output exists; pass --overwrite"],
            setup="existing:masks.png",
        )
    )
    for bad in ("ckpt_missing", "ckpt_empty", "ckpt_pickle_weights", "ckpt_stale_hash"):
        add(
            Case(
                f"segment-stack-{bad}",
                "segment-stack",
                ["--mask-model", ref(bad)],
                [ref(bad), BAD_CHECKPOINTS[bad][0]],
            )
        )
    add(
        Case(
            "segment-stack-fuse-two-stacks",
            "segment-stack",
            [
                "--input-stacks",
                "{stack}",
                "{stack}",
                "--output-stack-masks",
                "{out}/a.nii.gz",
                "{out}/b.nii.gz",
                "--fuse-masks",
            ],
            ["--fuse-masks: needs at least 3 stacks of one fetus, got 2"],
        )
    )
    add(
        Case(
            "segment-stack-thicknesses-without-fusion",
            "segment-stack",
            ["--thicknesses", "3"],
            ["--thicknesses: used only with --fuse-masks"],
        )
    )
    add(
        Case(
            "segment-stack-thickness-count",
            "segment-stack",
            [
                "--input-stacks",
                "{stack}",
                "{stack}",
                "{stack}",
                "--output-stack-masks",
                "{out}/a.nii.gz",
                "{out}/b.nii.gz",
                "{out}/c.nii.gz",
                "--fuse-masks",
                "--thicknesses",
                "3",
                "3",
            ],
            ["--thicknesses: got 2 values for 3 stacks"],
        )
    )
    for bad, problem in BAD_FILES.items():
        add(
            Case(
                f"segment-volume-input-volume-{bad}",
                "segment-volume",
                ["--input-volume", ref(bad)],
                [ref(bad), problem],
                setup="unreadable" if bad == "unreadable" else None,
            )
        )
    for case_id, changes, expect in (
        (
            "atlas-without-labels",
            ["--atlas-dir", "{atlas_good}"],
            ["{atlas_good}/GA30/parcellation.nii.gz is missing"],
        ),
        ("atlas-missing", ["--atlas-dir", "{out}/no-atlas"], ["{out}/no-atlas is not a folder"]),
        ("atlas-empty", ["--atlas-dir", "{atlas_empty}"], ["no GA*/srr.nii.gz volumes"]),
        ("age-zero", ["--gestational-age", "0"], ["--gestational-age", "a finite number > 0"]),
        ("measures-suffix", ["--output-measures", "{out}/m.csv"], ["m.csv", ".tsv or .json"]),
        ("report-suffix", ["--output-report", "{out}/r.txt"], ["r.txt", "written as .html"]),
        ("output-is-input", ["--output-labels", "{brain}"], ["{brain}", "given twice"]),
        ("mask-grid", ["--input-mask", "{small_mask}"], ["{brain}", "mask shape"]),
    ):
        add(Case(f"segment-volume-{case_id}", "segment-volume", changes, expect))
    for command in ("register", "reconstruct"):
        add(
            Case(
                f"{command}-fuse-given-masks",
                command,
                ["--fuse-masks"],
                ["--fuse-masks: only for automatic masks, and these stacks have masks given"],
            )
        )
        add(
            Case(
                f"{command}-fuse-otsu",
                command,
                ["--fuse-masks", "--auto-masks", "otsu"],
                ["--fuse-masks: needs --auto-masks network"],
                drop=["--stack-masks"],
            )
        )
        add(
            Case(
                f"{command}-fuse-one-stack",
                command,
                ["--fuse-masks"],
                ["--fuse-masks: needs at least 3 stacks of one fetus, got 1"],
                drop=["--stack-masks"],
            )
        )
    add(
        Case(
            "segment-stack-pose-model",
            "segment-stack",
            ["--mask-model", "{model}"],
            ["{model}", "not a brain-mask model"],
        )
    )
    for command in ("register", "reconstruct"):
        add(
            Case(
                f"{command}-auto-mask-model-missing",
                command,
                ["--mask-model", "{ckpt_missing}"],
                ["{ckpt_missing}", "checkpoint folder does not exist"],
                drop=["--stack-masks"],
            )
        )
    for command in ("register", "reconstruct"):
        add(
            Case(
                f"{command}-thickness-count",
                command,
                ["--thicknesses", "3", "4"],
                ["--thicknesses: got 2 values for 1 stacks"],
            )
        )

    # Checkpoints.
    for command, option in CHECKPOINT_OPTIONS.items():
        for bad, (message, evaluate_message) in BAD_CHECKPOINTS.items():
            add(
                Case(
                    f"{command}-{bad}",
                    command,
                    [*option, ref(bad)],
                    [ref(bad), evaluate_message if command == "evaluate" else message],
                    setup="unreadable_config" if bad == "ckpt_unreadable" else None,
                )
            )
    add(
        Case(
            "train-resume-pickle-training-state",
            "train",
            ["--output-dir", "{run_pickle_state}"],
            ["training_state.pt", "refused by the safe unpickler"],
        )
    )
    add(
        Case(
            "train-checkpoints-is-a-file",
            "train",
            [],
            ["checkpoints", "not a folder of checkpoints"],
            setup="checkpoints_file",
        )
    )

    # Other input files and folders.
    add(
        Case(
            "simulate-motion-missing",
            "simulate",
            ["--motion", "trajectories", "--motion-path", "{motion_missing}"],
            ["{motion_missing}", "not a fetal motion trajectory file"],
        )
    )
    add(
        Case(
            "simulate-motion-junk",
            "simulate",
            ["--motion", "trajectories", "--motion-path", "{motion_junk}"],
            ["{motion_junk}", "not a fetal motion trajectory file"],
        )
    )
    add(
        Case(
            "simulate-motion-pickle",
            "simulate",
            ["--motion", "trajectories", "--motion-path", "{motion_pickle}"],
            ["{motion_pickle}", "not a fetal motion trajectory file"],
        )
    )
    for bad, message in (
        ("missing", "not a slice folder"),
        ("no_slices", "no slice files"),
        ("thick_slices", "expected one slice"),
        ("bad_slices", "cannot read as NIfTI"),
    ):
        add(
            Case(
                f"predict-input-slices-{bad}",
                "predict",
                ["--input-slices", ref(bad)],
                [ref(bad), message],
                drop=["--input-stacks", "--stack-masks"],
            )
        )
    for command in ("train", "evaluate", "train-stack-pose"):
        for bad, message in (
            ("missing", "is not a folder"),
            ("brain", "is not a folder"),
            ("atlas_empty", "no GA*/srr.nii.gz volumes"),
            ("atlas_bad_name", "GAxx"),
            ("atlas_bad_srr", "cannot read as NIfTI"),
        ):
            add(
                Case(
                    f"{command}-atlas-dir-{bad}",
                    command,
                    ["--atlas-dir", ref(bad)],
                    ["--atlas-dir" if bad != "atlas_bad_srr" else "srr.nii.gz", message],
                    drop=[]
                    if command == "train-stack-pose"
                    else ["--input-volumes", "--input-masks"],
                )
            )

    for bad in ("motion_missing", "motion_junk", "motion_pickle"):
        add(
            Case(
                f"train-stack-pose-{bad.replace('_', '-')}",
                "train-stack-pose",
                ["--motion-path", ref(bad)],
                [ref(bad), "not a fetal motion trajectory file"],
            )
        )
    add(
        Case(
            "train-stack-pose-second-phase-too-long",
            "train-stack-pose",
            ["--fine-tune-steps", "1"],
            ["--fine-tune-steps must be < steps (1; 0 for one phase), got 1"],
        )
    )
    add(
        Case(
            "train-stack-pose-minutes-zero",
            "train-stack-pose",
            ["--minutes", "0"],
            ["--minutes must be > 0, got 0"],
        )
    )
    add(
        Case(
            "train-stack-pose-output-dir-is-a-file",
            "train-stack-pose",
            [],
            ["{out}/run", "not a folder"],
            setup="existing:run",
        )
    )
    for option in ("--atlas-volume", "--output-stack-poses"):
        add(
            Case(
                f"predict-slice-model-{option[2:]}",
                "predict",
                [option, "{out}/x.json" if option == "--output-stack-poses" else "{brain}"]
                + (["--atlas-mask", "{mask}"] if option == "--atlas-volume" else []),
                ["need a stack-pose model"],
            )
        )
    for argv in (["--registration", "atlas"], ["--registration", "cnn", "--model", "none"]):
        add(
            Case(
                f"reconstruct-{'-'.join(a.strip('-') for a in argv)}-without-atlas",
                "reconstruct",
                argv,
                ["--registration atlas needs --atlas-volume with --atlas-mask, or --atlas-dir"],
            )
        )
    add(
        Case(
            "reconstruct-atlas-volume-without-mask",
            "reconstruct",
            ["--registration", "cnn", "--atlas-volume", "{brain}"],
            ["--atlas-volume and --atlas-mask go together"],
        )
    )
    add(
        Case(
            "predict-atlas-dir-without-age",
            "predict",
            ["--atlas-dir", "{atlas_good}"],
            ["--atlas-dir needs the fetus's --gestational-age"],
        )
    )
    add(
        Case(
            "reconstruct-age-without-atlas-dir",
            "reconstruct",
            ["--registration", "cnn", "--gestational-age", "28"],
            ["--gestational-age chooses atlases from --atlas-dir"],
        )
    )
    add(
        Case(
            "reconstruct-atlas-dir-without-age",
            "reconstruct",
            ["--registration", "cnn", "--atlas-dir", "{atlas_good}"],
            ["--atlas-dir needs the fetus's --gestational-age"],
        )
    )
    add(
        Case(
            "reconstruct-atlas-dir-and-volume",
            "reconstruct",
            [
                *("--registration", "cnn", "--atlas-dir", "{atlas_good}"),
                *("--atlas-volume", "{brain}", "--atlas-mask", "{mask}"),
            ],
            ["give --atlas-volume or --atlas-dir, not both"],
        )
    )
    add(
        Case(
            "reconstruct-atlas-dir-empty",
            "reconstruct",
            [
                *("--registration", "cnn", "--atlas-dir", "{atlas_empty}"),
                *("--gestational-age", "28"),
            ],
            ["--atlas-dir", "no GA*/srr.nii.gz volumes"],
        )
    )
    add(
        Case(
            "reconstruct-atlas-volumes-one-mask",
            "reconstruct",
            [
                *("--registration", "cnn"),
                *("--atlas-volume", "{brain}", "{brain}"),
                *("--atlas-mask", "{mask}"),
            ],
            ["one mask per --atlas-volume", "2 volumes and 1 masks"],
        )
    )

    # Numbers: argparse refuses values of the wrong sign (status 2); the library the rest.
    argparse_values = {
        "simulate": [
            ("--num-stacks", "0"),
            ("--num-stacks", "-2"),
            ("--thickness", "0"),
            ("--thickness", "-1"),
            ("--slice-spacing", "0"),
            ("--in-plane-resolution", "0"),
            ("--in-plane-resolution", "nan"),
            ("--interleave", "0"),
            ("--slice-time", "-1"),
            ("--phantom-ga", "0"),
        ],
        "sample": [
            ("--num-slices", "0"),
            ("--size", "0"),
            ("--size", "-4"),
            ("--spacing", "0"),
            ("--spacing", "-1"),
            ("--thickness", "0"),
            ("--phantom-ga", "-1"),
        ],
        "train": [
            ("--size", "0"),
            ("--spacing", "0"),
            ("--width", "0"),
            ("--depth", "0"),
            ("--steps", "0"),
            ("--steps", "-5"),
            ("--batch-size", "0"),
            ("--lr", "0"),
            ("--lr", "-1"),
            ("--checkpoint-every", "0"),
            ("--keep-checkpoints", "0"),
            ("--log-every", "0"),
            ("--thickness-range", "0", "2"),
            ("--spacing-range", "-1", "1"),
        ],
        "predict": [("--batch-size", "0")],
        "evaluate": [
            ("--num-slices", "0"),
            ("--thickness", "0"),
            ("--batch-size", "0"),
            ("--phantom-ga", "0"),
        ],
        "register": [("--thicknesses", "0"), ("--thicknesses", "-3")],
        "demo": [("--train-steps", "0"), ("--phantom-ga", "0")],
        "demo-loss": [("--num-poses", "0"), ("--steps", "0"), ("--learning-rate", "0")],
    }
    argparse_values["reconstruct"] = argparse_values["register"]
    for command, values in argparse_values.items():
        for option, *value in values:
            add(
                Case(
                    f"{command}-{option[2:]}={','.join(value)}",
                    command,
                    [option, *value],
                    [f"argument {option}: must be"],
                )
            )
    # Values argparse accepts and a configuration refuses: the message names the option
    # (svr.cli.common.option_errors), says what it accepts and repeats the value.
    library_values = {
        "simulate": [
            ("--noise", "-1", "--noise must be a finite number >= 0, got -1.0"),
            ("--noise", "inf", "--noise must be a finite number >= 0, got inf"),
            ("--motion-scale", "nan", "--motion-scale must be a finite number >= 0, got nan"),
            ("--rotation-deg", "-1", "--rotation-deg must be a finite number >= 0, got -1.0"),
            ("--rotation-deg", "inf", "--rotation-deg must be a finite number >= 0"),
            ("--translation-mm", "-1", "--translation-mm must be a finite number >= 0"),
            ("--translation-mm", "inf", "--translation-mm must be a finite number >= 0"),
            ("--bias-field", "-0.5", "--bias-field must be a finite number >= 0, got -0.5"),
            ("--bias-field", "inf", "--bias-field must be a finite number >= 0"),
            ("--signal-voids", "1.5", "--signal-voids must be in [0, 1], got 1.5"),
            ("--stack-turn-deg", "10", "5", "--stack-turn-deg must be a tuple (low, high)"),
            (
                "--stack-turn-deg",
                "0",
                "270",
                "--stack-turn-deg must be a tuple (low, high) of finite numbers with "
                "0 <= low <= high <= 180, got 0.0 270.0",
            ),
        ],
        "sample": [
            ("--min-brain-fraction", "-0.1", "--min-brain-fraction must be in [0, 1)"),
            ("--min-brain-fraction", "1", "--min-brain-fraction must be in [0, 1)"),
            ("--min-brain-fraction", "nan", "--min-brain-fraction must be in [0, 1)"),
        ],
        "train": [
            ("--warmup-steps", "-1", "--warmup-steps must be an integer >= 0, got -1"),
            ("--workers", "-1", "--workers must be an integer >= 0, got -1"),
            ("--weight-decay", "-1", "--weight-decay must be a finite number >= 0, got -1.0"),
            ("--weight-decay", "inf", "--weight-decay must be a finite number >= 0, got inf"),
            ("--shift-mm", "-1", "--shift-mm must be a finite number >= 0, got -1.0"),
            ("--shift-mm", "inf", "--shift-mm must be a finite number >= 0"),
            ("--deform-mm", "-2", "--deform-mm must be a finite number >= 0, got -2.0"),
            ("--thickness-range", "3", "1", "--thickness-range must be a tuple (low, high)"),
            ("--size", "16", "--size must be a tuple of 2 integers >= 32, got 16 16"),
            ("--width", "4", "--width must be an integer >= 8, got 4"),
            ("--seed", "-1", "--seed must be an integer >= 0, got -1"),
            ("--metric-weights", "1", "2", "3", "--metric-weights must be a tuple of 6 or 36"),
            ("--metric-weights", "1", "1", "1", "1", "1", "-1", "--metric-weights"),
            ("--metric-weights", "1", "1", "1", "1", "1", "nan", "--metric-weights must be"),
            ("--pose-sampling", "grid", "--rotation", "uniform", "--rotation must be 'euler'"),
        ],
        "train-stack-pose": [
            ("--width", "2", "--width must be an integer >= 4, got 2"),
            ("--head", "coords", "--loss", "anchor", "--loss must be se3 with the coords head"),
        ],
        "evaluate": [("--min-brain-fraction", "1.5", "--min-brain-fraction must be in [0, 1)")],
        "register": [
            (
                "--output-resolution",
                "0",
                "--output-resolution must be a finite number > 0, got 0.0",
            ),
            ("--output-resolution", "-1", "--output-resolution must be a finite number > 0"),
            ("--output-resolution", "inf", "--output-resolution must be a finite number > 0"),
            ("--iterations", "0", "--iterations must be an integer >= 1, got 0"),
            ("--sr-iterations", "0", "--sr-iterations must be a non-empty tuple of integers >= 1"),
            ("--sr-regularization", "-0.1", "--sr-regularization must be"),
            ("--svr-iterations", "0", "--svr-iterations must be an integer >= 1, got 0"),
            ("--packets", "0", "--packets must be an integer >= 1, got 0"),
            ("--template", "-1", "--template must be an integer >= 0, got -1"),
            ("--template", "5", "--template 5: must be a stack index"),
            ("--ncc-threshold", "nan", "--ncc-threshold must be in [-1, 1], got nan"),
            ("--ncc-threshold", "2", "--ncc-threshold must be in [-1, 1], got 2.0"),
            ("--seed", "-1", "--seed must be an integer >= 0, got -1"),
        ],
        "demo": [("--seed", "-1", "--seed must be an integer >= 0, got -1")],
        "demo-loss": [],
        "bids": [("--ncc-threshold", "2", "sub-01: --ncc-threshold must be in [-1, 1], got 2.0")],
    }
    library_values["reconstruct"] = library_values["register"]
    for command, values in library_values.items():
        for option, *value, message in values:
            add(
                Case(
                    f"{command}-{option[2:]}={','.join(value)}",
                    command,
                    [option, *value],
                    [message],
                )
            )
    for command in sorted(set(BASE) - CPU_ONLY):
        add(
            Case(
                f"{command}-device-tpu",
                command,
                ["--device", "tpu"],
                ["--device: unknown device 'tpu'"],
            )
        )

    # svr bids: its output folder is positional and made as mkdir -p; a finished participant is
    # skipped, not an error.
    add(
        Case(
            "bids-output-unwritable",
            "bids",
            [],
            ["{out}/derivatives: output folder {out} is not writable"],
            setup="unwritable",
        )
    )
    add(
        Case(
            "bids-masks-dir-missing",
            "bids",
            ["--masks-dir", "{out}/no-masks"],
            ["--masks-dir {out}/no-masks: no such folder"],
        )
    )
    # Outputs: missing folder, unwritable folder, existing output without --overwrite.
    for command, (option, name) in OUTPUT_OPTION.items():
        add(
            Case(
                f"{command}-output-unwritable",
                command,
                [option, "{out}/" + name],
                ["{out}", "is not writable"],
                setup="unwritable",
            )
        )
        if command not in ("train", "train-stack-pose"):  # runs' folders are made as mkdir -p
            add(
                Case(
                    f"{command}-output-folder-missing",
                    command,
                    [option, "{out}/no/such/" + name],
                    ["{out}/no/such", "does not exist"],
                )
            )
        existing = EXISTING[command]
        if existing is not None:
            name, option = existing
            add(
                Case(
                    f"{command}-output-exists",
                    command,
                    [option, "{out}/" + name.rstrip("/")],
                    ["{out}/" + name.rstrip("/"), "output exists; pass --overwrite"],
                    setup="existing:" + name,
                )
            )
    add(
        Case(
            "sample-dataset-exists",
            "sample",
            [],
            ["{out}/dataset", "output exists; pass --overwrite"],
            setup="existing:dataset/",
        )
    )
    add(
        Case(
            "train-output-dir-is-a-file",
            "train",
            [],
            ["{out}/run", "not a folder"],
            setup="existing:run",
        )
    )
    add(
        Case(
            "train-no-resume-without-overwrite",
            "train",
            ["--no-resume"],
            ["{out}/run", "holds checkpoints; resume, or pass --overwrite"],
            setup="run_with_checkpoint",
        )
    )
    for case_id, changes, expect, drop in (
        ("stage-assemble-without-model", ["--stage", "assemble"], ["--output-model: required"],
         ["--output-model"]),
        ("stage-localiser-with-model", ["--stage", "localiser"], ["--output-model: written by"],
         []),
        ("no-atlas", [], ["--atlas-dir: required to train"], ["--atlas-dir"]),
        ("atlas-missing", ["--atlas-dir", "{missing}"], ["--atlas-dir", "is not a folder"], []),
        ("atlas-empty", ["--atlas-dir", "{atlas_empty}"], ["no GA*/srr.nii.gz volumes"], []),
        ("grazing-only", ["--grazing-only"],
         ["--grazing-only must be False without partial-volume masks, got True"], []),
        ("intensity-curves", ["--intensity-curves", "1.5"],
         ["--intensity-curves must be in [0, 1], got 1.5"], []),
        ("output-dir-is-a-file", [], ["{out}/run", "not a folder"], []),
    ):  # fmt: skip
        add(
            Case(
                f"train-brain-mask-{case_id}",
                "train-brain-mask",
                changes,
                expect,
                drop=drop,
                setup="existing:run" if case_id == "output-dir-is-a-file" else None,
            )
        )
    for case_id, changes, expect, drop in (
        ("checkpoint-missing", ["--checkpoint", "{ckpt_missing}"],
         ["--checkpoint", "{ckpt_missing}", "does not exist"], []),
        ("no-training-command", [], ["--training-command", "records no training command"],
         ["--training-command"]),
        ("empty-data", ["--data", ""], ["--data: empty"], []),
        ("output-is-the-checkpoint", ["--output-model", "{model}", "--overwrite"],
         ["--output-model {model}: the same path as --checkpoint"], []),
        ("not-a-pose-model", ["--checkpoint", "{masker}"], ["{masker}"], []),
    ):  # fmt: skip
        add(Case(f"export-model-{case_id}", "export-model", changes, expect, drop=drop))
    add(
        Case(
            "demo-loss-option-without-loss-only",
            "demo",
            ["--num-poses", "2"],
            ["--num-poses: applies only with --loss-only"],
        )
    )
    for command in ("register", "reconstruct"):
        add(
            Case(
                f"{command}-output-suffix",
                command,
                ["--output-transforms", "{out}/t.txt"],
                ["--output-transforms {out}/t.txt: must end in .csv or .json"],
            )
        )
    add(
        Case(
            "predict-output-suffix",
            "predict",
            ["--output-poses", "{out}/poses.txt"],
            ["--output-poses {out}/poses.txt: must end in .csv or .json"],
        )
    )
    return cases


CASES = _cases()


# --- running a case ------------------------------------------------------------------------------


def _argv(case: Case, names: dict[str, str]) -> list[str]:
    tokens = BASE[case.command].split()
    for option in case.drop:
        at = tokens.index(option)
        end = at + 1
        while end < len(tokens) and not tokens[end].startswith("--"):
            end += 1
        del tokens[at:end]
    changes = list(case.changes)
    while changes:
        option = changes.pop(0)
        values = []
        while changes and not changes[0].startswith("--"):
            values.append(changes.pop(0))
        if option in tokens:
            at = tokens.index(option)
            end = at + 1
            while end < len(tokens) and not tokens[end].startswith("--"):
                end += 1
            tokens[at:end] = [option, *values]
        else:
            tokens += [option, *values]
    return [token.format(**names) for token in tokens]


def _snapshot(folder: Path) -> dict[str, bytes | None]:
    """Every file (its bytes) and folder (``None``) under ``folder``."""
    snapshot: dict[str, bytes | None] = {}
    for path in sorted(folder.rglob("*")):
        snapshot[str(path.relative_to(folder))] = None
        if path.is_file():
            with path.open("rb") as f:  # not read_bytes(), which a case patches
                snapshot[str(path.relative_to(folder))] = f.read()
    return snapshot


def _setup(case: Case, names: dict[str, str], out: Path, monkeypatch) -> None:
    if case.setup is None:
        return
    kind, _, arg = case.setup.partition(":")
    if kind == "existing":
        if arg.endswith("/"):
            (out / arg).mkdir()
            (out / arg / "keep.txt").write_text("keep me")
        else:
            (out / arg).write_bytes(b"keep me \x00\x01")
    elif kind == "unwritable":  # tests run as root: pretend that the output folder is read-only
        real = os.access

        def access(path, mode, *args, **kwargs):
            if mode & os.W_OK and Path(path).resolve().is_relative_to(out.resolve()):
                return False
            return real(path, mode, *args, **kwargs)

        monkeypatch.setattr(svr.files.os, "access", access)
    elif kind == "unreadable":  # the same for reading one input file
        real = os.access
        target = Path(names["unreadable"]).resolve()

        def access(path, mode, *args, **kwargs):
            if mode & os.R_OK and Path(path).resolve() == target:
                return False
            return real(path, mode, *args, **kwargs)

        monkeypatch.setattr(svr.image.os, "access", access)
    elif kind == "unreadable_config":
        real_read = pathlib.Path.read_bytes
        target = (Path(names["ckpt_unreadable"]) / CHECKPOINT_CONFIG).resolve()

        def read_bytes(self):
            if self.resolve() == target:
                raise PermissionError(13, "Permission denied", str(self))
            return real_read(self)

        monkeypatch.setattr(pathlib.Path, "read_bytes", read_bytes)
    elif kind == "run_with_checkpoint":
        shutil.copytree(names["good_step"], out / "run" / "checkpoints" / checkpoint_name(1))
    elif kind == "checkpoints_file":
        (out / "run").mkdir()
        (out / "run" / "checkpoints").write_text("not a folder")
    else:
        raise AssertionError(f"unknown setup {case.setup}")


def _run(argv: list[str], capsys) -> tuple[int, str]:
    capsys.readouterr()
    try:
        code = main(argv)
    except SystemExit as exit_:
        code = exit_.code
    return code, capsys.readouterr().err


def _params() -> list:
    return [
        pytest.param(
            case,
            id=case.id,
            marks=[pytest.mark.xfail(strict=True, reason=case.xfail)] if case.xfail else [],
        )
        for case in CASES
    ]


def _never_called(*args, **kwargs):
    raise AssertionError("the computation started: the bad input was not refused up front")


@pytest.mark.parametrize("case", _params())
def test_bad_input_is_refused_cleanly(case: Case, env, tmp_path, capsys, monkeypatch):
    out = tmp_path / "out"
    out.mkdir()
    names = {**env, "out": str(out)}
    command = BASE[case.command].split()[0]
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(pipeline, "reconstruct", _never_called)  # register, reconstruct
    monkeypatch.setattr(recon_demo, "simulate_case", _never_called)  # demo
    monkeypatch.setattr(brain_mask, "segment_stack", _never_called)  # segment-stack
    monkeypatch.setattr(mask_recipe, "train_stage", _never_called)  # train-brain-mask
    _setup(case, names, out, monkeypatch)
    argv = _argv(case, names)
    before, inputs_before = _snapshot(out), _snapshot(Path(env["root"]))

    code, err = _run([*argv, "-q"], capsys)

    lines = [line for line in err.splitlines() if line.strip()]
    prefix = f"svr {command}: error: "
    assert code == case.code, err
    assert "Traceback" not in err, err
    assert lines and lines[-1].startswith(prefix), err
    assert len(lines) == 1, err  # bad usage too: one line, no usage dump
    for expected in case.expect:
        assert expected.format(**names).lower() in lines[-1].lower(), err
    assert _snapshot(out) == before
    assert _snapshot(Path(env["root"])) == inputs_before
    assert not Path(env["marker"]).exists()

    if case.code == 1:  # the same error with --verbose: its traceback, then the same line
        code, err = _run([*argv, "--verbose"], capsys)
        assert code == 1, err
        assert "Traceback (most recent call last)" in err, err
        assert err.rstrip().splitlines()[-1] == lines[-1]
        assert _snapshot(out) == before
        assert not Path(env["marker"]).exists()


def test_every_subcommand_is_swept():
    assert {BASE[case.command].split()[0] for case in CASES} == set(SUBCOMMANDS)
    ids = {case.id for case in CASES}
    for key in BASE:
        assert f"{key}-output-unwritable" in ids
        assert key in CPU_ONLY or f"{key}-device-tpu" in ids


def test_real_process_prints_one_line_or_a_traceback(env, tmp_path):
    """The console entry point, where logging and nibabel's own handler write to stderr.

    One line without --verbose (nibabel's header message is not printed beside it); the traceback
    and the same line with it.
    """
    out = tmp_path / "case"
    argv = [sys.executable, "-m", "svr", "simulate", "--output-dir", str(out)]
    argv += ["--input-volume", env["bad_header"], "--input-mask", env["mask"], "--device", "cpu"]
    quiet = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert quiet.returncode == 1
    assert quiet.stderr.count("\n") == 1, quiet.stderr
    assert quiet.stderr.startswith(
        f"svr simulate: error: {env['bad_header']}: cannot read as NIfTI"
    )
    verbose = subprocess.run([*argv, "-v"], capture_output=True, text=True, timeout=120)
    assert verbose.returncode == 1
    assert "Traceback (most recent call last)" in verbose.stderr
    assert verbose.stderr.rstrip().splitlines()[-1] == quiet.stderr.strip()
    assert not out.exists() and not Path(env["marker"]).exists()


@pytest.mark.parametrize("key", list(BASE))
def test_the_base_invocations_are_good(key, env, tmp_path, capsys, monkeypatch):
    """Control: without a change each base invocation gets past every check (so each case fails
    for its own bad input). The long-running commands stop at a sentinel instead of computing."""
    out = tmp_path / "out"
    out.mkdir()
    names = {**env, "out": str(out)}
    monkeypatch.setattr(pipeline, "reconstruct", _never_called)
    monkeypatch.setattr(recon_demo, "simulate_case", _never_called)
    monkeypatch.setattr(brain_mask, "segment_stack", _never_called)
    monkeypatch.setattr(mask_recipe, "train_stage", _never_called)
    monkeypatch.setattr(tissue_app, "segment_volume", _never_called)
    argv = _argv(Case("control", key, [], []), names)
    sentinel = ("register", "reconstruct", "demo", "segment-stack", "bids", "train-brain-mask")
    if key in (*sentinel, "segment-volume"):
        with pytest.raises(AssertionError, match="the computation started"):
            main([*argv, "-q"])
    else:
        assert main([*argv, "-q"]) == 0, capsys.readouterr().err
