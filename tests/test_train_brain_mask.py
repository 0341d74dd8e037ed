"""``svr train-brain-mask`` and :mod:`svr.masking.recipe`: the command trains what the library
does, resumes, assembles the model with its provenance, and refuses bad inputs in one line.

The networks and scenes are shrunk (a 32-pixel localiser canvas, 60-voxel scenes) so that a run
takes seconds; the recipe's own settings are checked against the library without training.
"""

from __future__ import annotations

import dataclasses
import json
import shlex

import pytest
import torch
from synthetic import ellipsoid_brain

import svr.masking.recipe as recipe_module
from svr.cli import build_parser, main
from svr.image import Image, load_nifti, save_nifti
from svr.masking import BrainMaskConfig, load_brain_masker
from svr.masking.recipe import (
    TILED_MASK_CONFIG,
    MaskerRecipe,
    recorded_recipe,
    train_stage,
)
from svr.masking.train import (
    BrainMaskTrainingConfig,
    StageData,
    make_examples,
    stage_data,
    train_network,
)
from svr.models.checkpoint import latest_checkpoint, load_checkpoint
from svr.models.segmentation import SegmentationConfig
from svr.sampling.scenes import SceneConfig
from svr.sampling.volume import atlas_volume_paths, load_volumes

TINY_DATA = StageData(SceneConfig(extent_mm=240.0, spacing_mm=4.0), (2.0, 3.0), (30.0, 60.0))


def _tiny_mask_config(recipe: MaskerRecipe) -> BrainMaskConfig:
    segmenter = SegmentationConfig(
        recipe.segmenter_width, 2, in_channels=1 + 2 * recipe.segmenter_context
    )
    return BrainMaskConfig(
        localiser_mm=6.0,
        localiser_size=32,
        segmenter_mm=3.0,
        segmenter_size=48,
        localiser=SegmentationConfig(4, 2),
        segmenter=segmenter,
        localiser_tiles=recipe.tiles,
    )


@pytest.fixture
def tiny(monkeypatch):
    """Shrink every recipe's networks and scenes (their settings still record them)."""
    monkeypatch.setattr(MaskerRecipe, "mask_config", _tiny_mask_config)
    monkeypatch.setattr(recipe_module, "stage_data", lambda *args, **kwargs: TINY_DATA)


@pytest.fixture(scope="module")
def atlas(tmp_path_factory):
    """One atlas age: a synthetic brain with its mask and tissue labels."""
    folder = tmp_path_factory.mktemp("atlas") / "GA28"
    folder.mkdir()
    image, mask = ellipsoid_brain(40, 2.0, (30.0, 36.0, 26.0), seed=3, origin_mm=(-39.0,) * 3)
    save_nifti(image, folder / "srr.nii.gz")
    save_nifti(mask, folder / "mask.nii.gz")
    labels = (mask.data > 0.5).float() + (image.data > 0.6).float()
    save_nifti(Image(labels, image.affine), folder / "parcellation.nii.gz")
    return folder.parent


def _command(atlas, run, *options: str) -> list[str]:
    return [
        "train-brain-mask", "--atlas-dir", str(atlas), "--output-dir", str(run),
        "--cases", "1", "--steps", "2", "--quiet", *options,
    ]  # fmt: skip


def _one_line_error(capsys, *words: str) -> None:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for word in words:
        assert word in err, err


def test_the_default_recipe_is_the_default_masker_and_the_tiled_one_the_shipped_settings():
    assert MaskerRecipe().mask_config() == BrainMaskConfig()
    tiled = MaskerRecipe(tiles=True, segmenter_width=12).mask_config()
    shipped = load_brain_masker("default").config
    assert tiled == shipped
    assert {k: getattr(shipped, k) for k in TILED_MASK_CONFIG} == TILED_MASK_CONFIG
    recipe = MaskerRecipe(tiles=True, faces=True, segment_all_slices=True)
    data = recipe.stage_data("segmenter")
    expected = stage_data("segmenter", tiles=True, faces=True)
    assert data == dataclasses.replace(expected, segment_all_slices=True)


def test_the_command_trains_what_the_library_does_and_assembles_the_model(
    tiny, atlas, tmp_path, capsys
):
    run, model = tmp_path / "run", tmp_path / "model"
    command = _command(atlas, run, "--output-model", str(model), "--label-intensities")
    assert main(command) == 0
    assert capsys.readouterr().out.strip() == f"wrote {model}"
    recipe = MaskerRecipe(
        training=BrainMaskTrainingConfig(cases=1, steps=2), label_intensities=True
    )
    brains, _ = load_volumes(atlas_volume_paths(atlas))
    labels = [load_nifti(atlas / "GA28" / "parcellation.nii.gz").data.round().long()]
    masker = load_brain_masker(model)
    for stage in ("localiser", "segmenter"):
        folder = run / stage
        assert latest_checkpoint(folder).name == "step_000000002"
        assert json.loads((folder / "settings.json").read_text()) == recipe.settings(stage)
        examples = make_examples(
            brains,
            stage,
            recipe.mask_config(),
            recipe.training,
            TINY_DATA,
            tissue_labels=labels,
        )
        net = train_network(examples, getattr(recipe.mask_config(), stage), recipe.training)
        for name, value in net.state_dict().items():
            assert torch.equal(value, load_checkpoint(latest_checkpoint(folder)).state_dict[name])
            stored = getattr(masker, stage).state_dict()[name]
            torch.testing.assert_close(stored, value, rtol=1e-3, atol=1e-3)  # float16
    config = load_checkpoint(model).config
    assert config["provenance"]["localiser"]["checkpoint"] == "step_000000002"
    card = (model / "README.md").read_text()
    assert "--label-intensities" in card and "--stage assemble" in card
    # The same command again: nothing left to train; the model is not replaced without
    # --overwrite, and is the same with it.
    assert main(command) == 1
    _one_line_error(capsys, "--overwrite")
    before = load_checkpoint(model).state_dict
    assert main([*command, "--overwrite"]) == 0
    again = load_checkpoint(model).state_dict
    assert all(torch.equal(again[k], v) for k, v in before.items())
    # Other settings in the same run folder: refused, the folder named.
    assert main(_command(atlas, run, "--steps", "3", "--stage", "localiser")) == 1
    _one_line_error(capsys, "started with other settings", "settings.json")


def test_stages_trained_apart_assemble_to_the_model_of_one_run(tiny, atlas, tmp_path, capsys):
    one, apart = tmp_path / "one", tmp_path / "apart"
    assert main(_command(atlas, one, "--output-model", str(tmp_path / "m1"))) == 0
    for stage in ("localiser", "segmenter"):
        assert main(_command(atlas, apart, "--stage", stage)) == 0
    assert "trained the segmenter in" in capsys.readouterr().out
    assemble = ["train-brain-mask", "--stage", "assemble", "--output-dir", str(apart)]
    assert main([*assemble, "--output-model", str(tmp_path / "m2"), "--quiet"]) == 0
    a, b = load_checkpoint(tmp_path / "m1").state_dict, load_checkpoint(tmp_path / "m2").state_dict
    assert all(torch.equal(a[k], b[k]) for k in a)
    # Assembling for another network shape than the one trained: refused.
    wider = [*assemble, "--segmenter-width", "6", "--output-model", str(tmp_path / "m3")]
    assert main(wider) == 1
    _one_line_error(capsys, "trained for another mask config")
    assert not (tmp_path / "m3").exists()


def test_the_model_card_commands_give_back_each_network_recipe(tmp_path):
    """The card's command for each network, parsed as the command line, is the recorded recipe."""
    from svr.cli.train_brain_mask import _commands

    recipe = MaskerRecipe(
        training=BrainMaskTrainingConfig(cases=80, steps=3000, seed=2, intensity_curves=0.5),
        tiles=True,
        segmenter_width=12,
        segmenter_context=1,
        label_intensities=True,
        partial_volume_masks=True,
        grazing_only=True,
    )
    run = tmp_path / "run"
    for stage in ("localiser", "segmenter"):
        (run / stage).mkdir(parents=True)
        (run / stage / "settings.json").write_text(json.dumps(recipe.settings(stage)))
    assert recorded_recipe(run, "segmenter") == recipe
    assert recorded_recipe(run, "localiser") == dataclasses.replace(
        recipe, segmenter_width=8, segmenter_context=0
    )
    parser = build_parser()
    args = parser.parse_args(
        ["train-brain-mask", "--output-dir", str(run), "--output-model", "m", "--atlas-dir", "a"]
    )
    lines = _commands(args, recipe)
    assert lines[2] == "wait" and len(lines) == 4
    for line, stage in zip(lines[:2], ("localiser", "segmenter"), strict=True):
        words = shlex.split(line.removeprefix("OMP_NUM_THREADS=1 ").removesuffix(" &"))
        parsed = parser.parse_args(words[1:])
        assert parsed.stage == stage
        again = MaskerRecipe(
            training=BrainMaskTrainingConfig(
                cases=parsed.cases,
                steps=parsed.steps,
                seed=parsed.seed,
                intensity_curves=parsed.intensity_curves,
            ),
            tiles=parsed.tiles,
            segmenter_width=parsed.segmenter_width,
            segmenter_context=parsed.segmenter_context,
            label_intensities=parsed.label_intensities,
            partial_volume_masks=parsed.partial_volume_masks,
            grazing_only=parsed.grazing_only,
        )
        assert again.settings(stage) == recipe.settings(stage)
    assemble = parser.parse_args(shlex.split(lines[3])[1:])
    assert (assemble.segmenter_width, assemble.segmenter_context, assemble.tiles) == (12, 1, True)


def test_a_run_folder_of_other_settings_is_refused_by_the_library(tiny, atlas, tmp_path):
    recipe = MaskerRecipe(training=BrainMaskTrainingConfig(cases=1, steps=1))
    train_stage(recipe, "localiser", tmp_path, atlas)
    other = dataclasses.replace(recipe, faces=True)
    with pytest.raises(ValueError, match="started with other settings"):
        train_stage(other, "localiser", tmp_path, atlas)


@pytest.mark.parametrize(
    ("options", "words"),
    [
        (["--stage", "assemble"], ["--output-model: required with --stage assemble"]),
        (["--stage", "localiser", "--output-model", "MODEL"], ["--output-model", "localiser"]),
        (["--grazing-only"], ["--grazing-only must be False without partial-volume masks"]),
        (["--thick-skulls", "--tight-heads"], ["--thick-skulls must be False with tight heads"]),
        (["--intensity-curves", "2"], ["--intensity-curves must be"]),
        (["--atlas-dir", "MISSING"], ["--atlas-dir"]),
        (["--stage", "assemble", "--output-model", "MODEL"], ["holds no checkpoint"]),
    ],
)
def test_bad_inputs_are_one_line_errors_before_any_work(
    tiny, atlas, tmp_path, capsys, options, words
):
    command = [
        "train-brain-mask", "--output-dir", str(tmp_path / "run"), "--atlas-dir", str(atlas),
    ]  # fmt: skip
    options = [str(tmp_path / o) if o in ("MODEL", "MISSING") else o for o in options]
    assert main([*command, *options]) == 1
    _one_line_error(capsys, *words)
    assert not (tmp_path / "run" / "localiser").exists()
    assert not (tmp_path / "MODEL").exists()


def test_an_existing_model_folder_is_refused_before_training(tiny, atlas, tmp_path, capsys):
    (tmp_path / "model").mkdir()
    command = _command(atlas, tmp_path / "run", "--output-model", str(tmp_path / "model"))
    assert main(command) == 1
    _one_line_error(capsys, "--overwrite")
    assert not (tmp_path / "run").exists()
    assert main(["train-brain-mask", "--output-dir", str(tmp_path / "r2"), "--quiet"]) == 1
    _one_line_error(capsys, "--atlas-dir: required to train")
