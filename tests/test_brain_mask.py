"""Automatic brain masks (svr.masking, svr segment-stack): geometry, files, a tiny model.

The tiny model is trained here, on simulated scenes around the procedural phantom, in about 20 s;
it must find the brain of an unseen scene with Dice >= 0.8 (issue 14).
"""

from __future__ import annotations

import dataclasses
import logging
import pickle
from pathlib import Path

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk  # noqa: N813
import torch
from scipy import ndimage

from svr.cli import main
from svr.image import Image, save_mask_like
from svr.masking import (
    BrainMaskConfig,
    BrainMasker,
    BrainNotFoundError,
    load_brain_masker,
    save_brain_masker,
    segment_stack,
)
from svr.masking import train as brain_mask_train
from svr.masking.canvas import (
    canvas_to_slices,
    neighbour_slices,
    slices_to_canvas,
    tile_centres,
)
from svr.masking.segment import _localise
from svr.masking.train import (
    BrainMaskTrainingConfig,
    StageData,
    TrainingExamples,
    _case_simulation,
    dice_bce_loss,
    intensity_curve,
    make_examples,
    stage_data,
    train_network,
)
from svr.models.checkpoint import CheckpointError
from svr.models.pretrained import MAX_MODEL_BYTES, brain_mask_model_path
from svr.models.segmentation import SegmentationConfig
from svr.sampling.scenes import SceneConfig, make_scene
from svr.sampling.simulate import SimulationConfig, simulate_case
from svr.sampling.volume import load_volumes

TINY = BrainMaskConfig(
    localiser_mm=6.0,
    localiser_size=32,
    segmenter_mm=3.0,
    segmenter_size=48,
    localiser=SegmentationConfig(4, 2),
    segmenter=SegmentationConfig(4, 2),
    min_volume_ml=1.0,
)
TINY_DATA = StageData(SceneConfig(extent_mm=240.0, spacing_mm=4.0), (2.0, 3.0), (30.0, 60.0))


def dice(a: torch.Tensor, b: torch.Tensor) -> float:
    return float(2 * (a & b).sum() / (a.sum() + b.sum()))


@pytest.fixture(scope="module")
def phantom():
    volumes, _ = load_volumes([], phantom_ages=(28.0,))
    return volumes[0]


@pytest.fixture(scope="module")
def tiny_masker(phantom) -> BrainMasker:
    """Both networks trained on six simulated scenes each (no bare brains)."""
    masker = BrainMasker(TINY)
    config = BrainMaskTrainingConfig(
        cases=8, bare_fraction=0.0, steps=400, batch_size=8, learning_rate=5e-3
    )
    for stage in ("localiser", "segmenter"):
        examples = make_examples([phantom], stage, TINY, config, TINY_DATA)
        net = train_network(examples, getattr(TINY, stage), config)
        getattr(masker, stage).load_state_dict(net.state_dict())
    return masker.eval()


@pytest.fixture(scope="module")
def unseen_stack(phantom):
    """A stack of a scene the tiny model was not trained on, and its true brain mask."""
    scene = make_scene(phantom, TINY_DATA.scene, seed=99)
    config = SimulationConfig(num_stacks=1, in_plane_mm=2.5, thickness_mm=3.5, margin_mm=45.0)
    stack = simulate_case(scene, config).stacks[0]
    return stack.image, stack.mask.data > 0.5


# --- canvases ------------------------------------------------------------------------------------


def test_canvas_geometry_matches_the_closed_form():
    """A single bright voxel lands on the canvas pixel (i - c) * spacing / pixel + (S - 1) / 2."""
    slices = torch.zeros(1, 1, 40, 50)
    slices[0, 0, 30, 13] = 1.0
    spacing = torch.tensor([1.5, 0.75], dtype=torch.float64)
    centre = torch.tensor([20.0, 25.0], dtype=torch.float64)
    canvas = slices_to_canvas(slices, spacing, centre, size=49, pixel_mm=1.5, mode="nearest")
    assert float(canvas.sum()) == 1.0
    a, b = np.unravel_index(int(canvas[0, 0].argmax()), (49, 49))
    assert (a, b) == ((30 - 20) * 1.5 / 1.5 + 24, (13 - 25) * 0.75 / 1.5 + 24)


def test_canvas_round_trip_is_the_identity_where_covered():
    slices = torch.rand(3, 1, 24, 30, dtype=torch.float64)
    spacing = torch.tensor([1.2, 1.2], dtype=torch.float64)
    centre = torch.tensor([11.5, 14.5], dtype=torch.float64)
    canvas = slices_to_canvas(slices, spacing, centre, size=32, pixel_mm=1.2)
    back = canvas_to_slices(canvas, spacing, centre, 1.2, (24, 30))
    torch.testing.assert_close(back, slices)


def test_per_slice_centres_shift_each_canvas():
    slices = torch.zeros(2, 1, 20, 20)
    slices[:, 0, 10, 10] = 1.0
    centres = torch.tensor([[10.0, 10.0], [6.0, 10.0]], dtype=torch.float64)
    canvas = slices_to_canvas(
        slices, torch.ones(2, dtype=torch.float64), centres, 16, 1.0, mode="nearest"
    )
    peaks = [np.unravel_index(int(c.argmax()), (16, 16)) for c in canvas[:, 0]]
    assert peaks[0][0] - peaks[1][0] == -4


@pytest.mark.parametrize(
    ("n", "step", "tile", "expected"),
    [
        # 320 voxels of 1.125 mm (360 mm) with 192 mm tiles: 3 centres, the outer tiles' edges
        # on the field of view's edges (voxel -0.5 and 319.5), the centres 84 mm apart.
        (320, 1.125, 192.0, [192 / 2 / 1.125 - 0.5, 159.5, 319 - (192 / 2 / 1.125 - 0.5)]),
        (100, 1.0, 192.0, [49.5]),  # the tile holds the field of view: one, in the middle
        (100, 2.0, 100.0, [24.5, 49.5, 74.5]),  # 200 mm: 3 tiles of 100 mm, 50 mm apart
    ],
)
def test_tile_centres_match_the_closed_form(n, step, tile, expected):
    spacing = torch.tensor([step, 1.0], dtype=torch.float64)
    centres = tile_centres((n, 1), spacing, tile)
    torch.testing.assert_close(centres[:, 0], torch.tensor(expected, dtype=torch.float64))
    if len(expected) > 1:  # neighbours overlap by at least half a tile
        assert float(centres[:, 0].diff().max()) * step <= tile / 2 + 1e-9


class _Threshold(torch.nn.Module):
    """A stand-in localiser: logits 40 (x - 0.5), i.e. brain where the canvas is above 0.5."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 40 * (x - 0.5)


def test_tiled_localiser_maps_each_tile_back_to_its_place():
    """A bright square in one corner of a wide field of view comes back where it is."""
    slices = torch.zeros(2, 1, 300, 200)
    slices[:, :, 250:280, 20:50] = 1.0
    spacing = torch.tensor([1.2, 1.2], dtype=torch.float64)
    config = BrainMaskConfig(localiser_mm=1.2, localiser_size=64, localiser_tiles=True)
    assert len(tile_centres((300, 200), spacing, 64 * 1.2)) > 20
    found = _localise(_Threshold(), slices, spacing, config) > 0.5
    expected = slices > 0.5
    assert int((found != expected).sum()) <= 2 * 4 * 30  # at most the square's rim differs
    assert bool(found[:, :, 252:278, 22:48].all())
    assert not bool(found[:, :, :240].any()) and not bool(found[:, :, :, 60:].any())


def test_tiled_localiser_blends_to_the_tiles_common_value():
    class Constant(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return torch.full_like(x, 0.3)

    slices = torch.rand(3, 1, 90, 70)
    spacing = torch.tensor([2.0, 1.5], dtype=torch.float64)
    config = BrainMaskConfig(localiser_mm=2.0, localiser_size=32, localiser_tiles=True)
    out = _localise(Constant(), slices, spacing, config)
    torch.testing.assert_close(out, torch.full_like(out, float(torch.sigmoid(torch.tensor(0.3)))))


def test_intensity_curve_matches_numpy_interp():
    generator = torch.Generator().manual_seed(0)
    x = 1.8 * torch.rand(3, 1, 8, 8, generator=generator)
    knots = torch.rand(3, 8, generator=generator).cumsum(1)
    out = intensity_curve(x, knots)
    grid = np.linspace(0.0, 2.0, 8)
    for b in range(3):
        expected = np.interp(x[b].numpy(), grid, knots[b].numpy())
        np.testing.assert_allclose(out[b].numpy(), expected, rtol=1e-5, atol=1e-6)
    identity = torch.linspace(0.0, 2.0, 8).expand(3, 8)
    torch.testing.assert_close(intensity_curve(x, identity), x)


def test_tiled_stage_data_spreads_the_localiser_canvases():
    plain, tiled = stage_data("localiser"), stage_data("localiser", tiles=True)
    assert not plain.shift_per_slice and plain.centre_shift_mm == 60.0
    assert tiled.shift_per_slice and tiled.centre_shift_mm > plain.centre_shift_mm
    assert tiled.scene.spacing_mm < plain.scene.spacing_mm
    segmenter = stage_data("segmenter", tiles=True)
    assert segmenter.scene.skull_in_mask and not stage_data("segmenter").scene.skull_in_mask


def _changed_fields(a: SceneConfig, b: SceneConfig) -> set[str]:
    """The names of the fields in which two scene configs differ."""
    return {f.name for f in dataclasses.fields(a) if getattr(a, f.name) != getattr(b, f.name)}


@pytest.mark.parametrize("stage", ["localiser", "segmenter"])
def test_tight_heads_change_only_the_head_layers(stage):
    usual = stage_data(stage, tiles=True)
    tight = stage_data(stage, tiles=True, tight_heads=True)
    assert _changed_fields(usual.scene, tight.scene) == {
        "csf_mm",
        "skull_mm",
        "skull_intensity",
        "scalp_mm",
    }
    assert tight.scene.csf_mm[1] < usual.scene.csf_mm[1]
    assert tight.scene.skull_mm[0] < usual.scene.skull_mm[0]
    assert tight.scene.scalp_mm[0] < usual.scene.scalp_mm[0]
    assert dataclasses.replace(tight, scene=usual.scene) == usual


@pytest.mark.parametrize("stage", ["localiser", "segmenter"])
def test_thick_skulls_change_only_the_skull_and_scalp(stage):
    usual = stage_data(stage, tiles=True)
    thick = stage_data(stage, tiles=True, thick_skulls=True)
    assert _changed_fields(usual.scene, thick.scene) == {"skull_mm", "skull_intensity", "scalp_mm"}
    assert thick.scene.skull_mm[1] > usual.scene.skull_mm[1]
    assert thick.scene.skull_intensity[1] > usual.scene.skull_intensity[1]
    assert thick.scene.scalp_mm[0] < usual.scene.scalp_mm[0] and thick.scene.scalp_mm[1] < 4.0
    assert dataclasses.replace(thick, scene=usual.scene) == usual
    assert thick.scene.skull_in_mask == (stage == "segmenter")
    with pytest.raises(ValueError, match="'thick_skulls' and 'tight_heads' exclude each other"):
        stage_data(stage, tiles=True, thick_skulls=True, tight_heads=True)


@pytest.mark.parametrize("stage", ["localiser", "segmenter"])
def test_faces_cords_and_partial_volume_masks_change_one_field_each(stage):
    usual = stage_data(stage, tiles=True)
    assert not usual.scene.face and usual.mask_fraction is None
    faced = stage_data(stage, tiles=True, faces=True)
    assert faced.scene == dataclasses.replace(usual.scene, face=True)
    assert dataclasses.replace(faced, scene=usual.scene) == usual
    cord = stage_data(stage, tiles=True, spinal_cord=True)
    assert cord.scene == dataclasses.replace(usual.scene, spinal_cord=True)
    partial = stage_data(stage, tiles=True, partial_volume=True)
    assert partial == dataclasses.replace(usual, mask_fraction=0.2)
    config = _case_simulation(partial, False, np.random.default_rng(0), 1)
    assert config.mask_fraction == 0.2 and config.grazing_ratio is None
    grazing = stage_data(stage, tiles=True, partial_volume=True, grazing_only=True)
    assert grazing == dataclasses.replace(partial, grazing_ratio=0.5)
    config = _case_simulation(grazing, False, np.random.default_rng(0), 1)
    assert (config.mask_fraction, config.grazing_ratio) == (0.2, 0.5)
    with pytest.raises(ValueError, match="'grazing_only' needs 'partial_volume'"):
        stage_data(stage, tiles=True, grazing_only=True)


class _Above(torch.nn.Module):
    """A stand-in network: brain where the canvas is above ``level``."""

    def __init__(self, level: float) -> None:
        super().__init__()
        self.level = level

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 200 * (x - self.level)


@pytest.mark.parametrize(("margin", "slices"), [(2, (6, 12)), (None, (2, 17))])
def test_slice_margin_sets_the_segmented_slices(margin, slices):
    """The localiser sees the brightest slices 8-10; the segmenter segments ``margin`` beyond
    them, or every slice with ``None``."""
    data = torch.zeros(64, 64, 20)
    disc = (torch.arange(64)[:, None] - 32) ** 2 + (torch.arange(64)[None, :] - 32) ** 2 < 15**2
    data[(*disc.nonzero(as_tuple=True), slice(2, 18))] = 0.5
    data[(*disc.nonzero(as_tuple=True), slice(8, 11))] = 1.0
    data[0, 0, :] = 0.01  # positive background voxels for the normalisation
    config = BrainMaskConfig(
        localiser_mm=2.0,
        localiser_size=64,
        segmenter_mm=2.0,
        segmenter_size=64,
        slice_margin=margin,
    )
    masker = BrainMasker(config)
    masker.localiser, masker.segmenter = _Above(0.75), _Above(0.3)  # type: ignore[assignment]
    affine = torch.diag(torch.tensor([2.0, 2.0, 3.0, 1.0], dtype=torch.float64))
    mask = segment_stack(Image(data, affine), masker, device="cpu").mask
    found = mask.any(0).any(0).nonzero()[:, 0]
    assert (int(found.min()), int(found.max())) == slices


@pytest.mark.parametrize("per_slice", [False, True])
def test_localiser_canvas_centres_are_drawn_per_stack_or_per_slice(phantom, monkeypatch, per_slice):
    centres = []

    def recording(slices, spacing, centre, size, pixel_mm, mode="bilinear"):
        centres.append(centre)
        return slices_to_canvas(slices, spacing, centre, size, pixel_mm, mode)

    monkeypatch.setattr(brain_mask_train, "slices_to_canvas", recording)
    data = dataclasses.replace(TINY_DATA, shift_per_slice=per_slice)
    config = BrainMaskTrainingConfig(cases=1, bare_fraction=0.0)
    make_examples([phantom], "localiser", TINY, config, data)
    inputs = centres[::2]  # each stack's canvases, then its targets at the same centres
    assert all(torch.equal(a, b) for a, b in zip(inputs, centres[1::2], strict=True))
    for centre in inputs:
        if per_slice:
            assert centre.dim() == 2 and len(torch.unique(centre[:, 0])) == centre.shape[0]
        else:
            assert centre.shape == (2,)


def test_config_without_tiles_loads_as_one_canvas():
    data = BrainMaskConfig().to_dict()
    del data["localiser_tiles"]  # configs written before tiles existed
    assert BrainMaskConfig.from_dict(data).localiser_tiles is False
    every = BrainMaskConfig(slice_margin=None)
    assert BrainMaskConfig.from_dict(every.to_dict()) == every


def test_neighbour_slices_match_a_loop_with_the_ends_repeated():
    slices = torch.rand(5, 1, 4, 3, dtype=torch.float64)
    for context in (1, 2, 6):
        out = neighbour_slices(slices, context)
        assert out.shape == (5, 1 + 2 * context, 4, 3)
        for k in range(5):
            for c in range(1 + 2 * context):
                source = min(max(k - context + c, 0), 4)
                assert torch.equal(out[k, c], slices[source, 0]), (context, k, c)
    assert neighbour_slices(slices, 0) is slices


@pytest.mark.parametrize(
    ("shape", "context", "message"),
    [
        ((5, 2, 4, 3), 1, "'slices' must be"),
        ((0, 1, 4, 3), 1, "'slices' must be"),
        ((5, 1, 4, 3), -1, "'context' must be"),
        ((5, 1, 4, 3), True, "'context' must be"),
    ],
)
def test_neighbour_slices_name_a_bad_argument(shape, context, message):
    with pytest.raises(ValueError, match=message):
        neighbour_slices(torch.zeros(shape), context)


def test_segmenter_channels_set_the_context_and_round_trip():
    config = BrainMaskConfig(segmenter=SegmentationConfig(4, 2, in_channels=5))
    assert config.segmenter_context == 2 and BrainMaskConfig().segmenter_context == 0
    assert BrainMaskConfig.from_dict(config.to_dict()) == config
    data = BrainMaskConfig().to_dict()
    del data["segmenter"]["in_channels"]  # configs written before 2.5D segmenters
    assert BrainMaskConfig.from_dict(data).segmenter.in_channels == 1


@pytest.mark.parametrize(
    ("field", "net", "message"),
    [
        ("localiser", SegmentationConfig(4, 2, in_channels=3), "'localiser.in_channels' must be 1"),
        (
            "segmenter",
            SegmentationConfig(4, 2, in_channels=2),
            "'segmenter.in_channels' must be odd",
        ),
    ],
)
def test_config_names_bad_input_channels(field, net, message):
    with pytest.raises(ValueError, match=message):
        BrainMaskConfig(**{field: net})


def test_canvas_rejects_bad_shapes():
    with pytest.raises(ValueError, match="'slices' must be"):
        slices_to_canvas(torch.zeros(1, 1, 1, 5), torch.ones(2), torch.zeros(2), 16, 1.0)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("localiser_mm", 0.0, "'localiser_mm' must be a finite number > 0"),
        ("segmenter_mm", float("nan"), "'segmenter_mm'"),
        ("localiser_size", 100, "'localiser_size' must be a positive multiple of 16"),
        ("threshold", 1.0, "'threshold' must be in"),
        ("min_volume_ml", -1.0, "'min_volume_ml'"),
        ("percentile", 0.0, "'percentile'"),
        ("localiser_tiles", "yes", "'localiser_tiles' must be a bool"),
        ("slice_margin", -1, "'slice_margin' must be None or an integer >= 0"),
        ("max_volume_ml", 5.0, "'max_volume_ml' must be a finite number > 'min_volume_ml'"),
        ("max_volume_ml", float("inf"), "'max_volume_ml'"),
        ("max_stack_fraction", 0.0, "'max_stack_fraction' must be in"),
        ("max_stack_fraction", 1.5, "'max_stack_fraction' must be in"),
    ],
)
def test_config_names_the_bad_field(field, value, message):
    with pytest.raises(ValueError, match=message):
        BrainMaskConfig(**{field: value})


def test_loss_is_low_for_a_perfect_prediction_and_high_for_its_opposite():
    target = torch.zeros(2, 1, 8, 8)
    target[:, :, 2:6, 2:6] = 1
    good = dice_bce_loss(20 * (2 * target - 1), target)
    bad = dice_bce_loss(-20 * (2 * target - 1), target)
    assert float(good) < 0.05 < 1.5 < float(bad)


# --- the tiny model ------------------------------------------------------------------------------


def test_tiny_model_finds_the_brain_of_an_unseen_scene(tiny_masker, unseen_stack):
    image, truth = unseen_stack
    result = segment_stack(image, tiny_masker, name="unseen")
    assert result.mask.shape == truth.shape and result.mask.dtype == torch.bool
    assert dice(result.mask, truth) >= 0.8
    assert result.volume_ml == pytest.approx(float(result.mask.sum() * image.spacing.prod()) / 1000)


def test_a_2_5d_segmenter_blind_to_its_neighbours_gives_the_2d_mask(tiny_masker, unseen_stack):
    """The tiny segmenter's weights on the middle channel, zeros on the neighbours' channels:
    the same probabilities as the 2D model, so the middle channel is the slice itself."""
    image, _ = unseen_stack
    wide = dataclasses.replace(TINY, segmenter=SegmentationConfig(4, 2, in_channels=3))
    masker = BrainMasker(wide)
    masker.localiser.load_state_dict(tiny_masker.localiser.state_dict())
    state = dict(tiny_masker.segmenter.state_dict())
    first = "down.0.0.weight"
    weight = torch.zeros(state[first].shape[0], 3, *state[first].shape[2:])
    weight[:, 1:2] = state[first]
    state[first] = weight
    masker.segmenter.load_state_dict(state)
    flat = segment_stack(image, tiny_masker, name="2d")
    deep = segment_stack(image, masker.eval(), name="2.5d")
    torch.testing.assert_close(deep.probability, flat.probability, rtol=0, atol=1e-5)
    assert torch.equal(deep.mask, flat.mask)
    # with the weights on a neighbour's channel instead, the probabilities change
    weight = torch.zeros_like(weight)
    weight[:, 0:1] = state[first][:, 1:2]
    masker.segmenter.load_state_dict({**state, first: weight})
    shifted = segment_stack(image, masker.eval(), name="2.5d").probability
    assert float((shifted - flat.probability).abs().max()) > 0.1


def test_2_5d_examples_hold_the_2d_canvas_in_the_middle_and_neighbours_around(phantom):
    config = BrainMaskTrainingConfig(cases=2, bare_fraction=0.0, seed=5)
    flat = make_examples([phantom], "segmenter", TINY, config, TINY_DATA)
    wide = dataclasses.replace(TINY, segmenter=SegmentationConfig(4, 2, in_channels=3))
    deep = make_examples([phantom], "segmenter", wide, config, TINY_DATA)
    assert deep.inputs.shape == (flat.inputs.shape[0], 3, *flat.inputs.shape[2:])
    assert torch.equal(deep.inputs[:, 1:2], flat.inputs)
    assert torch.equal(deep.targets, flat.targets)
    # consecutive canvases of a stack: this one's lower neighbour is the previous one's slice
    follows = [
        torch.equal(deep.inputs[n, 0], deep.inputs[n - 1, 1])
        and torch.equal(deep.inputs[n - 1, 2], deep.inputs[n, 1])
        for n in range(1, deep.inputs.shape[0])
    ]
    assert sum(follows) >= len(follows) - 6  # (at most one break per stack: 2 cases, <= 3 each)


def test_2_5d_training_reverses_the_slice_order_of_some_batches(monkeypatch):
    import svr.masking.train as module

    seen = []
    real = module._augment

    def spy(x, generator, curves=0.0):
        seen.append(x.clone())
        return real(x, generator, curves)

    monkeypatch.setattr(module, "_augment", spy)
    order_draws = []  # torch.rand(1, ...): the only draw of size 1, the slice-order coin
    real_rand = torch.rand

    def counting_rand(*size, **kwargs):
        if size == (1,):
            order_draws.append(1)
        return real_rand(*size, **kwargs)

    monkeypatch.setattr(module.torch, "rand", counting_rand)
    generator = torch.Generator().manual_seed(0)
    slices = torch.rand(4, 1, 16, 16, generator=generator)
    inputs = torch.cat([slices, 2 + slices, 4 + slices], 1).half()  # channel means ~0.5, 2.5, 4.5
    examples = TrainingExamples(inputs, slices > 0.5)
    config = BrainMaskTrainingConfig(steps=12, batch_size=2)
    train_network(examples, SegmentationConfig(2, 1, in_channels=3), config)
    reversed_order = [bool(x[:, 0].mean() > x[:, 2].mean()) for x in seen]
    assert 0 < sum(reversed_order) < len(reversed_order)  # both orders seen
    assert all(float(x[:, 1].mean()) > 2 for x in seen)  # the middle stays in the middle
    assert len(order_draws) == 12  # one coin a step
    order_draws.clear()  # 2D: no coin, so 2D runs keep the random stream of the shipped weights
    train_network(TrainingExamples(inputs[:, :1], slices > 0.5), SegmentationConfig(2, 1), config)
    assert order_draws == []


def test_no_brain_is_an_error_naming_the_stack(tiny_masker, unseen_stack):
    """Whether the localiser or the segmenter finds nothing: an error, never an empty mask."""
    image, _ = unseen_stack
    for stage, message in (("localiser", "the localiser's"), ("segmenter", "the segmented")):
        blind = BrainMasker(TINY)
        blind.load_state_dict(tiny_masker.state_dict())
        with torch.no_grad():
            getattr(blind, stage).head.bias.fill_(-30.0)
        with pytest.raises(
            BrainNotFoundError, match=rf"^scan\.nii\.gz: no fetal brain found \({message}"
        ):
            segment_stack(image, blind, name="scan.nii.gz")


def test_a_mask_over_the_whole_field_of_view_is_an_error_naming_the_stack(tiny_masker):
    """A segmenter that takes everything gives an error, never a whole-image mask."""
    masker = BrainMasker(TINY)
    masker.load_state_dict(tiny_masker.state_dict())
    for net in (masker.localiser, masker.segmenter):
        torch.nn.init.constant_(net.head.bias, 50.0)  # every pixel brain
    stack = Image(torch.rand(30, 30, 16) + 1.0, torch.diag(torch.tensor([3.0, 3.0, 4.0, 1.0])))
    with pytest.raises(BrainNotFoundError, match=r"^whole: no fetal brain found .* % of the stack"):
        segment_stack(stack, masker.eval(), name="whole")
    # the volume bound alone (the mask covers the stack: 90 x 90 x 64 mm, 518 ml)
    loose = dataclasses.replace(TINY, max_stack_fraction=1.0, max_volume_ml=400.0)
    masker.config = loose
    with pytest.raises(BrainNotFoundError, match=r"518 ml .* at most 400 ml"):
        segment_stack(stack, masker.eval(), name="whole")


def test_bad_stacks_are_refused(tiny_masker, unseen_stack):
    image, _ = unseen_stack
    data = image.data.clone()
    data[3, 3, 3] = float("nan")
    with pytest.raises(ValueError, match=r"s\.nii: the stack has non-finite voxels"):
        segment_stack(Image(data, image.affine), tiny_masker, name="s.nii")
    with pytest.raises(ValueError, match=r"s\.nii: all voxels are zero"):
        segment_stack(Image(torch.zeros(8, 8, 3), image.affine), tiny_masker, name="s.nii")


def test_saved_masker_round_trips(tiny_masker, tmp_path):
    folder = save_brain_masker(tiny_masker, tmp_path / "m", {"note": "test"})
    loaded = load_brain_masker(folder)
    assert loaded.config == TINY
    for key, value in tiny_masker.state_dict().items():
        torch.testing.assert_close(
            loaded.state_dict()[key].float(), value.float(), atol=1e-2, rtol=1e-3
        )


# --- files and the command -----------------------------------------------------------------------

OBLIQUE = np.array(
    [
        [0.0, -1.1, 0.2, 40.5],
        [1.12, 0.0, 0.0, -20.25],
        [0.0, 0.05, 3.3, 7.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def _stack_file(path: Path, data: np.ndarray, four_d: bool = False) -> Path:
    image = nib.Nifti1Image(data[..., None] if four_d else data, OBLIQUE)
    image.set_qform(OBLIQUE, code=1)
    sform = OBLIQUE.copy()
    sform[:3, 3] += 0.001  # sform and qform differ slightly: both must be copied, not derived
    image.set_sform(sform, code=2)
    image.header.set_xyzt_units("mm", "sec")
    nib.save(image, path)
    return path


@pytest.mark.parametrize("four_d", [False, True])
def test_mask_header_equals_the_stack_header(tmp_path, four_d):
    stack = _stack_file(tmp_path / "s.nii.gz", np.random.rand(12, 10, 5).astype(np.float32), four_d)
    mask = np.zeros((12, 10, 5), dtype=bool)
    mask[3:7, 2:5, 1:4] = True
    out = save_mask_like(torch.from_numpy(mask), stack, tmp_path / "m.nii.gz")
    ref, got = nib.load(stack), nib.load(out)
    assert got.get_data_dtype() == np.uint8 and got.shape == (12, 10, 5)
    np.testing.assert_array_equal(np.asarray(got.dataobj), mask.astype(np.uint8))
    s_ref, s_code_ref = ref.header.get_sform(coded=True)
    s_got, s_code_got = got.header.get_sform(coded=True)
    q_ref, q_code_ref = ref.header.get_qform(coded=True)
    q_got, q_code_got = got.header.get_qform(coded=True)
    np.testing.assert_array_equal(s_got, s_ref)
    np.testing.assert_array_equal(q_got, q_ref)
    assert (s_code_got, q_code_got) == (s_code_ref, q_code_ref) == (2, 1)
    for field in ("quatern_b", "quatern_c", "quatern_d", "qoffset_x", "qoffset_y", "qoffset_z"):
        assert ref.header[field] == got.header[field]
    np.testing.assert_array_equal(ref.header["pixdim"][1:4], got.header["pixdim"][1:4])
    a, b = sitk.ReadImage(str(stack)), sitk.ReadImage(str(out))
    assert b.GetOrigin() == a.GetOrigin()[:3]
    assert b.GetSpacing() == a.GetSpacing()[:3]
    direction = np.reshape(a.GetDirection(), (a.GetDimension(),) * 2)[:3, :3]
    np.testing.assert_array_equal(np.reshape(b.GetDirection(), (3, 3)), direction)


def test_mask_of_the_wrong_shape_writes_nothing(tmp_path):
    stack = _stack_file(tmp_path / "s.nii.gz", np.random.rand(12, 10, 5).astype(np.float32))
    with pytest.raises(ValueError, match=r"mask shape \(4, 4, 4\) is not the grid"):
        save_mask_like(np.zeros((4, 4, 4)), stack, tmp_path / "m.nii.gz")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.nii.gz"]


def test_segment_stack_command_writes_masks_and_a_figure(tiny_masker, unseen_stack, tmp_path):
    image, truth = unseen_stack
    from svr.image import save_nifti

    stack = save_nifti(image, tmp_path / "stack.nii.gz")
    model = save_brain_masker(tiny_masker, tmp_path / "model")
    argv = [
        "segment-stack",
        "--input-stacks",
        str(stack),
        "--output-stack-masks",
        str(tmp_path / "mask.nii.gz"),
        "--output-qa",
        str(tmp_path / "qa.png"),
        "--mask-model",
        str(model),
        "--device",
        "cpu",
        "-q",
    ]
    assert main(argv) == 0
    written = nib.load(tmp_path / "mask.nii.gz")
    assert written.get_data_dtype() == np.uint8
    np.testing.assert_array_equal(written.affine, nib.load(stack).affine)
    assert dice(torch.from_numpy(np.asarray(written.dataobj) > 0), truth) >= 0.8
    assert (tmp_path / "qa.png").stat().st_size > 10_000
    before = (tmp_path / "mask.nii.gz").read_bytes()
    assert main(argv) == 1  # exists without --overwrite
    assert (tmp_path / "mask.nii.gz").read_bytes() == before
    assert main([*argv, "--overwrite"]) == 0


def test_no_brain_in_one_stack_writes_no_mask(
    tiny_masker, unseen_stack, tmp_path, capsys, monkeypatch
):
    """The second stack has no brain (its localiser sees none): no mask is written at all."""
    import svr.masking as module

    image, _ = unseen_stack
    from svr.image import save_nifti

    good = save_nifti(image, tmp_path / "good.nii.gz")
    empty = save_nifti(Image(image.data.flip(0), image.affine), tmp_path / "empty.nii.gz")
    blind = BrainMasker(TINY)
    blind.load_state_dict(tiny_masker.state_dict())
    with torch.no_grad():
        blind.localiser.head.bias.fill_(-30.0)
    real = module.segment_stack

    def segment(stack, masker, name, device=None):
        return real(stack, blind if name == str(empty) else masker, name, device)

    monkeypatch.setattr(module, "segment_stack", segment)
    model = save_brain_masker(tiny_masker, tmp_path / "model")
    before = sorted(p.name for p in tmp_path.iterdir())
    code = main(
        [
            "segment-stack",
            "--input-stacks",
            str(good),
            str(empty),
            "--output-stack-masks",
            str(tmp_path / "a.nii.gz"),
            str(tmp_path / "b.nii.gz"),
            "--mask-model",
            str(model),
            "-q",
        ]
    )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1 and len(err) == 1
    assert err[0].startswith(f"svr segment-stack: error: {empty}: no fetal brain found")
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_reconstruct_uses_automatic_masks_and_says_so(tiny_masker, phantom, tmp_path, caplog):
    """`svr register` without --stack-masks runs the masker; the log and QA name the source."""
    caplog.set_level(logging.INFO)  # as the command sets it outside pytest
    scene = make_scene(phantom, TINY_DATA.scene, seed=7)
    config = SimulationConfig(num_stacks=2, in_plane_mm=2.5, thickness_mm=3.5, margin_mm=45.0)
    from svr.image import save_nifti

    stacks = [
        str(save_nifti(s.image, tmp_path / f"s{n}.nii.gz"))
        for n, s in enumerate(simulate_case(scene, config).stacks)
    ]
    model = save_brain_masker(tiny_masker, tmp_path / "model")
    argv = ["register", "--input-stacks", *stacks, "--thicknesses", "3.5", "--iterations", "1"]
    argv += ["--sr-iterations", "1", "--output-resolution", "3", "--mask-model", str(model)]
    argv += ["--output-transforms", str(tmp_path / "t.csv"), "--output-log", str(tmp_path / "l")]
    argv += ["--output-qa", str(tmp_path / "qa.png"), "--registration", "stack"]
    assert main(argv) == 0
    log = (tmp_path / "l").read_text()
    assert "automatic brain mask (network)" in log
    assert f"(mask automatic (network, --mask-model {model}))" in log


def _three_stacks(phantom, tmp_path, seed: int):
    """Three stacks of an unseen scene (files) and their true masks."""
    from svr.image import save_nifti

    scene = make_scene(phantom, TINY_DATA.scene, seed=seed)
    config = SimulationConfig(num_stacks=3, in_plane_mm=2.5, thickness_mm=3.5, margin_mm=45.0)
    case = simulate_case(scene, config)
    paths = [str(save_nifti(s.image, tmp_path / f"s{n}.nii.gz")) for n, s in enumerate(case.stacks)]
    return paths, [s.mask.data > 0.5 for s in case.stacks]


def test_segment_stack_fuses_the_masks_of_one_fetus(tiny_masker, phantom, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    stacks, truths = _three_stacks(phantom, tmp_path, seed=99)
    model = save_brain_masker(tiny_masker, tmp_path / "model")
    outs = [str(tmp_path / f"m{n}.nii.gz") for n in range(3)]
    argv = ["segment-stack", "--input-stacks", *stacks, "--output-stack-masks", *outs]
    argv += ["--fuse-masks", "--thicknesses", "3.5", "--mask-model", str(model), "-q"]
    assert main(argv) == 0
    assert caplog.text.count("fused brain mask") == 3
    for stack, out, truth in zip(stacks, outs, truths, strict=True):
        written = nib.load(out)
        np.testing.assert_array_equal(written.affine, nib.load(stack).affine)
        assert dice(torch.from_numpy(np.asarray(written.dataobj) > 0), truth) >= 0.8


def test_register_fuses_automatic_masks_and_says_so(tiny_masker, phantom, tmp_path, caplog):
    caplog.set_level(logging.INFO)
    stacks, _ = _three_stacks(phantom, tmp_path, seed=7)
    model = save_brain_masker(tiny_masker, tmp_path / "model")
    argv = ["register", "--input-stacks", *stacks, "--thicknesses", "3.5", "--iterations", "1"]
    argv += ["--sr-iterations", "1", "--output-resolution", "3", "--mask-model", str(model)]
    argv += ["--output-transforms", str(tmp_path / "t.csv"), "--output-log", str(tmp_path / "l")]
    argv += ["--registration", "stack", "--fuse-masks"]
    assert main(argv) == 0
    log = (tmp_path / "l").read_text()
    assert "automatic brain masks fused across 3 stacks" in log
    assert f"(mask automatic (network, --mask-model {model}, fused across stacks))" in log
    assert "fuse: True" in log


# --- the shipped model ---------------------------------------------------------------------------

SHIPPED = brain_mask_model_path()


@pytest.mark.skipif(not SHIPPED.is_dir(), reason="no shipped brain-mask model")
def test_shipped_model_is_small_and_loads_without_running_code(monkeypatch):
    size = sum(p.stat().st_size for p in SHIPPED.iterdir() if p.name != "README.md")
    assert size <= MAX_MODEL_BYTES
    assert (SHIPPED / "README.md").is_file()

    def refuse(*args, **kwargs):
        raise AssertionError("loading the shipped model unpickled something")

    monkeypatch.setattr(pickle, "load", refuse)
    monkeypatch.setattr(pickle, "loads", refuse)
    monkeypatch.setattr(torch, "load", refuse)
    masker = load_brain_masker("default")
    assert isinstance(masker, BrainMasker) and not masker.training


def test_loading_a_pose_model_as_a_masker_is_refused():
    from svr.models.pretrained import default_model_path

    with pytest.raises(CheckpointError, match="not a brain-mask model"):
        load_brain_masker(default_model_path())


def test_training_resumes_exactly_from_its_checkpoint(tmp_path):
    """A run interrupted after step 4 and resumed ends where an uninterrupted run ends."""
    import shutil

    generator = torch.Generator().manual_seed(0)
    inputs = torch.rand(10, 1, 16, 16, generator=generator).half()
    examples = TrainingExamples(inputs, inputs.float() > 0.6)
    net_config = SegmentationConfig(2, 1)
    config = BrainMaskTrainingConfig(steps=6, batch_size=3, checkpoint_every=2)

    straight = train_network(examples, net_config, config, tmp_path / "run")
    assert sorted(p.name for p in (tmp_path / "run").iterdir()) == [
        "step_000000004",
        "step_000000006",
    ]
    shutil.rmtree(tmp_path / "run" / "step_000000006")  # as if stopped after step 4
    resumed = train_network(examples, net_config, config, tmp_path / "run")
    for key, value in straight.state_dict().items():
        torch.testing.assert_close(resumed.state_dict()[key], value, rtol=0, atol=0)


def test_examples_pass_each_brain_its_own_tissue_labels(phantom, monkeypatch):
    """With tissue labels, scenes get the labels of the brain drawn for them (about half)."""
    import svr.masking.train as module

    labels = [torch.ones(phantom.image.shape, dtype=torch.long) * (n + 1) for n in range(2)]
    brains = [phantom, phantom]
    passed = []
    real = module.make_scene

    def spy(brain, config, seed, tissue_labels=None):
        passed.append(tissue_labels)
        return real(brain, config, seed, tissue_labels)

    monkeypatch.setattr(module, "make_scene", spy)
    config = BrainMaskTrainingConfig(cases=6, bare_fraction=0.0)
    make_examples(brains, "segmenter", TINY, config, TINY_DATA, tissue_labels=labels)
    assert len(passed) == 6
    assert all(t is None or any(t is label for label in labels) for t in passed)
    assert 0 < sum(t is not None for t in passed) < 6


def test_examples_are_a_function_of_the_seed(phantom):
    """The training data behind a model are reproducible: same seed, same canvases."""
    config = BrainMaskTrainingConfig(cases=2, bare_fraction=0.5, seed=3)
    a = make_examples([phantom], "localiser", TINY, config, TINY_DATA)
    b = make_examples([phantom], "localiser", TINY, config, TINY_DATA)
    assert torch.equal(a.inputs, b.inputs) and torch.equal(a.targets, b.targets)
    other = BrainMaskTrainingConfig(cases=2, bare_fraction=0.5, seed=4)
    c = make_examples([phantom], "localiser", TINY, other, TINY_DATA)
    assert a.inputs.shape != c.inputs.shape or not torch.equal(a.inputs, c.inputs)


def test_clean_up_fills_holes_and_keeps_one_body_through_the_slices():
    from svr.masking import clean_up_mask

    mask = np.zeros((20, 20, 3), dtype=bool)
    mask[4:12, 4:12, :] = True
    mask[7:9, 7:9, 1] = False  # a hole (a ventricle)
    mask[15:18, 15:18, 1] = True  # a piece of one slice, apart from the brain: dropped
    mask[12:15, 4:6, 2] = True  # joins the brain in its own slice
    mask[15:17, 4:6, 1:3] = True  # joins the brain only through the next slice: kept
    out = clean_up_mask(mask.copy(), np.ones(3))
    assert out[7:9, 7:9, 1].all()
    assert not out[15:18, 15:18, 1].any()
    assert out[15:17, 4:6, 1].all() and out[12:15, 4:6, 2].all()
    assert out.sum() == mask.sum() + 4 - 9


def _solid_ellipsoid(shape, spacing, centre_mm, radii_mm):
    """Bool mask of voxels whose centres (index * spacing, mm) lie in an axis-aligned ellipsoid."""
    points = np.indices(shape).reshape(3, -1).T * np.asarray(spacing)
    local = (points - np.asarray(centre_mm)) / np.asarray(radii_mm)
    return ((local**2).sum(axis=1) <= 1).reshape(shape)


@pytest.mark.parametrize("spacing", [(1.0, 1.0, 1.0), (1.1, 0.9, 3.3)])
def test_open_mask_equals_scipy_opening_by_a_ball_in_mm(spacing):
    from svr.masking import open_mask

    rng = np.random.default_rng(2)
    mask = ndimage.gaussian_filter(rng.standard_normal((40, 36, 14)), 2.5) > 0
    mask[0:12, 0:10, 0:6] = True  # touches the array's border: outside counts as background
    radius = 3.5
    reach = [int(radius // step) for step in spacing]
    offsets = np.indices([2 * n + 1 for n in reach]).reshape(3, -1).T - np.array(reach)
    ball = (np.linalg.norm(offsets * np.array(spacing), axis=1) <= radius).reshape(
        [2 * n + 1 for n in reach]
    )
    expected = ndimage.binary_opening(mask, structure=ball)
    opened = open_mask(mask, np.array(spacing), radius)
    assert 0 < opened.sum() < mask.sum()
    np.testing.assert_array_equal(opened, expected)


def test_clean_up_opening_cuts_a_leak_and_a_bridged_piece_and_keeps_the_head():
    from svr.masking import clean_up_mask

    spacing = np.array([1.0, 1.0, 3.0])
    head = _solid_ellipsoid((110, 100, 26), spacing, (50.0, 50.0, 36.0), (30, 24, 27))
    leaky = head.copy()
    leaky[70:100, 47:53, 8:16] = True  # a leak along fluid: 6 mm thick, 20 mm out of the head
    leaky[48:52, 48:52, 21:23] = True  # a narrow bridge from the head's end ...
    leaky[30:70, 30:70, 23:26] = True  # ... to a piece of the body beyond it
    out = clean_up_mask(leaky, spacing, 8.0)
    assert out[head].mean() > 0.99
    assert not out[:, :, 23:].any()  # the piece beyond the bridge is gone
    assert not out[81:].any()  # the head ends at i = 80: the leak is gone
    assert (out & ~head).sum() < 0.05 * (leaky & ~head).sum()
    assert clean_up_mask(leaky, spacing, None).sum() == leaky.sum()  # no opening: all kept
    # Regrowing by 2.5 mm gives back the leak's first 2 mm beside the head, no more.
    regrown = clean_up_mask(leaky, spacing, 8.0, 2.5)
    assert regrown[out].all() and not regrown[:, :, 23:].any()
    assert regrown[82, 47:53, 12].all() and not regrown[83:].any()
    # A brain thinner than the ball (two slices): opening would remove it, so it is kept.
    slab = np.zeros((60, 60, 6), dtype=bool)
    slab[10:50, 10:50, 2:4] = True
    np.testing.assert_array_equal(clean_up_mask(slab, spacing, 8.0), slab)


def test_config_names_a_bad_opening_radius():
    for bad in (0.0, -1.0, float("inf"), True, "8"):
        with pytest.raises(ValueError, match="'opening_mm' must be None or a finite number > 0"):
            BrainMaskConfig(opening_mm=bad)
    assert BrainMaskConfig(opening_mm=8).opening_mm == 8
    for bad in (-1.0, float("nan"), None, False):
        with pytest.raises(ValueError, match="'regrow_mm' must be a finite number >= 0"):
            BrainMaskConfig(regrow_mm=bad)


def test_training_config_names_a_bad_curve_fraction():
    with pytest.raises(ValueError, match="'intensity_curves' must be in"):
        BrainMaskTrainingConfig(intensity_curves=1.5)


def test_training_with_intensity_curves_runs_and_differs(tmp_path):
    examples = TrainingExamples(torch.rand(6, 1, 16, 16).half(), torch.rand(6, 1, 16, 16) > 0.5)
    nets = [
        train_network(
            examples,
            SegmentationConfig(2, 2),
            BrainMaskTrainingConfig(steps=3, batch_size=2, intensity_curves=curves),
        )
        for curves in (0.0, 1.0)
    ]
    a, b = (torch.cat([p.flatten() for p in n.parameters()]) for n in nets)
    assert not torch.equal(a, b)


def test_segmenter_examples_from_every_slice_add_only_slices_without_brain(phantom):
    config = BrainMaskTrainingConfig(cases=1, bare_fraction=0.0, seed=5)
    brain_only = make_examples([phantom], "segmenter", TINY, config, TINY_DATA)
    every = dataclasses.replace(TINY_DATA, segment_all_slices=True)
    everything = make_examples([phantom], "segmenter", TINY, config, every)
    assert everything.inputs.shape[0] > brain_only.inputs.shape[0]
    with_brain = everything.targets.flatten(1).any(1)
    assert int(with_brain.sum()) == int(brain_only.targets.flatten(1).any(1).sum())
