"""A brain-mask training run: both networks trained in a run folder, then one model folder.

A run folder holds one sub-folder per network (``localiser/``, ``segmenter/``), each with
``settings.json`` (what the network's examples and weights depend on; a resumed run must match
it), ``examples.pt`` (its simulated canvases, made once) and the ``step_NNNNNNNNN`` checkpoints
of :func:`svr.masking.train.train_network` (the newest is resumed). :func:`train_stage` trains
one network (the shipped model's two were trained side by side, one process and one core each);
:func:`assemble_masker` puts the two into a model folder (:func:`svr.masking.save_brain_masker`)
with its provenance and a model card. ``svr train-brain-mask`` is the command over this module.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import torch

from svr.errors import ConfigFieldError
from svr.files import atomic_write_text
from svr.image import load_nifti
from svr.masking.config import BrainMaskConfig
from svr.masking.network import BrainMasker, save_brain_masker
from svr.masking.train import (
    BrainMaskTrainingConfig,
    Stage,
    StageData,
    TrainingExamples,
    make_examples,
    stage_data,
    train_network,
)
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.models.segmentation import BrainUNet, SegmentationConfig
from svr.sampling.volume import atlas_volume_paths, load_volumes
from svr.validation import check_bool, check_instance, check_int

__all__ = [
    "EXAMPLES",
    "SETTINGS",
    "STAGES",
    "TILED_MASK_CONFIG",
    "MaskerRecipe",
    "assemble_masker",
    "model_card",
    "recorded_recipe",
    "train_stage",
]

log = logging.getLogger(__name__)

STAGES: tuple[Stage, ...] = ("localiser", "segmenter")
"""The networks of a masker, in the order they run."""
SETTINGS = "settings.json"
"""In each network's folder: what its examples and weights depend on."""
EXAMPLES = "examples.pt"
"""In each network's folder: its simulated canvases and targets."""

TILED_MASK_CONFIG: dict[str, Any] = {
    "localiser_mm": 1.5,
    "localiser_size": 128,
    "localiser_tiles": True,
    "slice_margin": None,
    "opening_mm": 8.0,
    "regrow_mm": 3.0,
}
"""The :class:`BrainMaskConfig` fields of the tiled recipe (the shipped model's): the localiser
on 1.5 mm tiles of 192 mm covering the field of view, every slice segmented, the mask opened by
an 8 mm ball and regrown by 3 mm (chosen on held-out simulated stacks)."""

_STAGE_FIELDS = {
    "localiser": ("localiser_mm", "localiser_size", "localiser", "localiser_tiles"),
    "segmenter": ("segmenter_mm", "segmenter_size", "segmenter", "localiser_tiles"),
}
"""The mask-config fields a network's training depends on (the rest only matter at inference)."""

_FLAGS = (
    "label_intensities",
    "segment_all_slices",
    "tight_heads",
    "faces",
    "partial_volume_masks",
    "spinal_cord",
    "grazing_only",
    "thick_skulls",
)
"""The recipe's simulation switches, recorded by name in ``settings.json``."""


@dataclass(frozen=True)
class MaskerRecipe:
    """How both networks of a masker are trained.

    Attributes:
        training: Cases, steps, seed and intensity maps of each network's training.
        tiles: The tiled recipe (:data:`TILED_MASK_CONFIG`, :func:`~svr.masking.train.stage_data`
            with ``tiles``); else the first recipe (one 3 mm localiser canvas, masks inside the
            skull).
        segmenter_width: Channels of the segmenter's first level, >= 1.
        segmenter_context: Neighbouring slices on either side the segmenter sees (0: 2D), >= 0.
        label_intensities: Half of the scenes give the brain a random intensity per label of
            the atlas's ``parcellation.nii.gz`` (SynthSeg-style).
        segment_all_slices: The segmenter learns from every slice (``StageData`` field).
        tight_heads: Narrower CSF, fainter and thinner skulls and scalps (``stage_data``).
        faces: Heads with a face and eyes over a neck (``stage_data``).
        partial_volume_masks: Slice masks wherever a fifth of the slice's profile is brain.
        spinal_cord: Heads end at the skull base, the brainstem below being the cord.
        grazing_only: With ``partial_volume_masks``, only on the slices grazing the head's ends.
        thick_skulls: 2-5 mm grey skulls inside the masks under thin scalps.

    Raises:
        ConfigFieldError: On construction, naming the field, for a value of the wrong type or
            out of range, ``grazing_only`` without ``partial_volume_masks``, or
            ``thick_skulls`` with ``tight_heads``.
    """

    training: BrainMaskTrainingConfig = field(default_factory=BrainMaskTrainingConfig)
    tiles: bool = False
    segmenter_width: int = 8
    segmenter_context: int = 0
    label_intensities: bool = False
    segment_all_slices: bool = False
    tight_heads: bool = False
    faces: bool = False
    partial_volume_masks: bool = False
    spinal_cord: bool = False
    grazing_only: bool = False
    thick_skulls: bool = False

    def __post_init__(self) -> None:
        owner = "MaskerRecipe"
        check_instance(owner, "training", self.training, BrainMaskTrainingConfig)
        for name in ("tiles", *_FLAGS):
            check_bool(owner, name, getattr(self, name))
        check_int(owner, "segmenter_width", self.segmenter_width, minimum=1)
        check_int(owner, "segmenter_context", self.segmenter_context, minimum=0)
        if self.grazing_only and not self.partial_volume_masks:
            raise ConfigFieldError(
                owner, "grazing_only", "False without partial-volume masks", True
            )
        if self.thick_skulls and self.tight_heads:
            raise ConfigFieldError(owner, "thick_skulls", "False with tight heads", True)

    def mask_config(self) -> BrainMaskConfig:
        """The masker's canvases, networks and clean-up."""
        config = BrainMaskConfig(**(TILED_MASK_CONFIG if self.tiles else {}))
        segmenter = dataclasses.replace(
            config.segmenter,
            width=self.segmenter_width,
            in_channels=1 + 2 * self.segmenter_context,
        )
        return dataclasses.replace(config, segmenter=segmenter)

    def stage_data(self, stage: Stage) -> StageData:
        """The scenes and acquisitions of one network's examples."""
        data = stage_data(
            stage,
            self.tiles,
            self.tight_heads,
            faces=self.faces,
            partial_volume=self.partial_volume_masks,
            spinal_cord=self.spinal_cord,
            grazing_only=self.grazing_only,
            thick_skulls=self.thick_skulls,
        )
        if self.segment_all_slices:
            data = dataclasses.replace(data, segment_all_slices=True)
        return data

    def settings(self, stage: Stage) -> dict[str, Any]:
        """Everything one network's examples and weights depend on (its ``settings.json``)."""
        mask = self.mask_config().to_dict()
        return {
            "mask_config": {k: mask[k] for k in _STAGE_FIELDS[stage]},
            "train": asdict(self.training),
            **{name: getattr(self, name) for name in _FLAGS},
        }


def _read_settings(path: Path) -> dict[str, Any]:
    """A network's recorded settings, with the defaults of settings added since it was written."""
    # (runs recorded before a setting existed had its default)
    settings: dict[str, Any] = {
        **{name: False for name in _FLAGS},
        **json.loads(path.read_text(encoding="utf-8")),
    }
    mask = settings["mask_config"]
    for name in STAGES:
        if name in mask:  # (e.g. in_channels, added with 2.5D segmenters)
            mask[name] = asdict(SegmentationConfig(**mask[name]))
    return settings


def recorded_recipe(run_dir: str | os.PathLike[str], stage: Stage) -> MaskerRecipe | None:
    """The recipe a network of a run folder was trained with, or ``None`` if none is recorded.

    What the network's training does not depend on (the other network's shape) has its default.
    """
    path = Path(run_dir) / stage / SETTINGS
    if not path.exists():
        return None
    settings = _read_settings(path)
    mask = settings["mask_config"]
    recipe = MaskerRecipe(
        training=BrainMaskTrainingConfig(**settings["train"]),
        tiles=bool(mask["localiser_tiles"]),
        **{name: settings[name] for name in _FLAGS},
    )
    if "segmenter" not in mask:  # (the localiser's training does not depend on it)
        return recipe
    segmenter = mask["segmenter"]
    return dataclasses.replace(
        recipe,
        segmenter_width=segmenter["width"],
        segmenter_context=(segmenter["in_channels"] - 1) // 2,
    )


def _simulate_examples(
    recipe: MaskerRecipe,
    stage: Stage,
    atlas_dir: str | os.PathLike[str],
    progress: bool,
) -> TrainingExamples:
    """One network's examples, simulated from the atlas brains (no real scan is read)."""
    began = time.time()
    pairs = atlas_volume_paths(atlas_dir)
    brains, _ = load_volumes(pairs)
    tissue_labels = None
    if recipe.label_intensities:
        tissue_labels = [
            load_nifti(v.parent / "parcellation.nii.gz").data.round().long() for v, _ in pairs
        ]
    examples = make_examples(
        brains,
        stage,
        recipe.mask_config(),
        recipe.training,
        recipe.stage_data(stage),
        progress=progress,
        tissue_labels=tissue_labels,
    )
    log.info(
        "%d %s examples (brain %.2f %% of pixels) in %.0f s",
        examples.inputs.shape[0],
        stage,
        100 * float(examples.targets.float().mean()),
        time.time() - began,
    )
    return examples


def train_stage(
    recipe: MaskerRecipe,
    stage: Stage,
    run_dir: str | os.PathLike[str],
    atlas_dir: str | os.PathLike[str],
    *,
    progress: bool = False,
    device: str | torch.device = "cpu",
) -> BrainUNet:
    """Train (or resume training) one network of a masker in ``run_dir/stage``.

    The first call records the settings and simulates the examples (kept in the folder); a
    later call with the same recipe resumes from the newest checkpoint.

    Args:
        recipe: How the masker is trained.
        stage: ``"localiser"`` or ``"segmenter"``.
        run_dir: The run folder (created if missing).
        atlas_dir: The atlas folder (``GA*/srr.nii.gz`` and ``mask.nii.gz``, and
            ``parcellation.nii.gz`` for ``label_intensities``), read unless the examples are
            kept already.
        progress: Log progress (and show a bar over the simulated cases).
        device: Where the network trains.

    Returns:
        The trained network (eval mode).

    Raises:
        ValueError: If the folder holds a network trained with other settings.
    """
    folder = Path(run_dir) / stage
    settings = recipe.settings(stage)
    recorded = folder / SETTINGS
    if recorded.exists() and _read_settings(recorded) != settings:
        raise ValueError(
            f"{recorded}: this run folder was started with other settings "
            f"({json.loads(recorded.read_text(encoding='utf-8'))}); train in another one"
        )
    folder.mkdir(parents=True, exist_ok=True)
    atomic_write_text(recorded, json.dumps(settings, indent=1), overwrite=True)
    cache = folder / EXAMPLES
    if cache.exists():
        cached = torch.load(cache, weights_only=True)
        examples = TrainingExamples(cached["inputs"], cached["targets"])
    else:
        examples = _simulate_examples(recipe, stage, atlas_dir, progress)
        partial = cache.with_name(cache.name + ".partial")
        torch.save({"inputs": examples.inputs, "targets": examples.targets}, partial)
        os.replace(partial, cache)
    net_config = getattr(recipe.mask_config(), stage)
    net = train_network(examples, net_config, recipe.training, folder, progress, device)
    log.info("%s done: %s", stage, asdict(recipe.training))
    return net


def model_card(
    config: BrainMaskConfig,
    trained: dict[str, BrainMaskTrainingConfig],
    commands: Sequence[str],
) -> str:
    """A model folder's ``README.md``: the networks, their training and the commands.

    Args:
        config: The masker's configuration.
        trained: Each network's training (``"localiser"`` and ``"segmenter"``).
        commands: The commands that made the model, in order.
    """
    context = config.segmenter_context
    where = {
        "localiser": ", tiled over each slice's field of view" if config.localiser_tiles else "",
        "segmenter": " centred on the brain"
        + (f", with {context} neighbouring slices on either side" if context else ""),
    }
    networks, training = [], []
    for stage in STAGES:
        net: SegmentationConfig = getattr(config, stage)
        pixel, size = getattr(config, f"{stage}_mm"), getattr(config, f"{stage}_size")
        networks.append(
            f"- {stage}: width {net.width}, depth {net.depth}, on {pixel:g} mm canvases of "
            f"{size} pixels{where[stage]};"
        )
        t = trained[stage]
        training.append(
            f"- {stage}: {t.cases} cases, {t.steps} steps of {t.batch_size} canvases, seed "
            f"{t.seed}, random intensity maps on a fraction {t.intensity_curves:g} of them;"
        )
    return "\n".join(
        [
            "# Brain-mask model (`svr segment-stack --mask-model`)",
            "",
            "Two 2D U-Nets (`svr.models.segmentation.BrainUNet`; float16 safetensors and a JSON "
            "config, loaded by `svr.masking.load_brain_masker` without running code):",
            "",
            *networks,
            "",
            "**Training data.** Simulated only; no real scan was used: the brains of an atlas "
            "folder placed in random whole-uterus scenes (`svr.sampling.scenes.make_scene`, "
            "settings in `svr.masking.train.stage_data`) or alone, cut by the project's stack "
            "simulator.",
            "",
            *training,
            "",
            "**Reproduce** (each network resumes from its newest checkpoint):",
            "",
            *(f"    {command}" for command in commands),
            "",
        ]
    )


def assemble_masker(
    recipe: MaskerRecipe,
    run_dir: str | os.PathLike[str],
    model_dir: str | os.PathLike[str],
    *,
    command: str,
    commands: Sequence[str] = (),
    overwrite: bool = False,
) -> Path:
    """Write the model folder of a run's two networks (their newest checkpoints).

    Args:
        recipe: The recipe the networks were trained with (its mask config is the model's).
        run_dir: The run folder.
        model_dir: The model folder to create (float16 weights, config with provenance,
            ``README.md``).
        command: The command that assembles the model, recorded in the provenance.
        commands: The commands that made the model, in order, for the model card.
        overwrite: Whether an existing ``model_dir`` may be replaced.

    Returns:
        ``model_dir``.

    Raises:
        ValueError: If a network has no checkpoint, or was trained for another mask config.
        OutputExistsError: If ``model_dir`` exists and ``overwrite`` is false.
    """
    masker = BrainMasker(recipe.mask_config())
    provenance: dict[str, Any] = {"command": command}
    trained: dict[str, BrainMaskTrainingConfig] = {}
    for stage in STAGES:
        folder = Path(run_dir) / stage
        newest = latest_checkpoint(folder)
        if newest is None:
            raise ValueError(f"{folder}: holds no checkpoint; train the {stage} first")
        recorded = folder / SETTINGS
        wanted = recipe.settings(stage)["mask_config"]
        if recorded.exists() and _read_settings(recorded)["mask_config"] != wanted:
            raise ValueError(f"{recorded}: the {stage} was trained for another mask config")
        checkpoint = load_checkpoint(newest)
        getattr(masker, stage).load_state_dict(checkpoint.state_dict)
        provenance[stage] = {"checkpoint": newest.name, "train": checkpoint.config["train"]}
        trained[stage] = BrainMaskTrainingConfig(**checkpoint.config["train"])
    out = save_brain_masker(masker, model_dir, provenance, overwrite=overwrite)
    card = model_card(masker.config, trained, commands)
    atomic_write_text(out / "README.md", card, overwrite=True)
    return out
