"""Label-map synthesis (svr.sampling.synthesis) and the tissue labels of canonical volumes."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy import ndimage
from synthetic import ellipsoid_brain

from svr.errors import ConfigFieldError
from svr.image import Image, save_nifti
from svr.sampling.deform import warp_channels
from svr.sampling.synthesis import (
    SynthesisConfig,
    gaussian_blur,
    label_maps,
    synthesize,
    synthesize_volume,
)
from svr.sampling.volume import (
    ATLAS_LABELS,
    VolumeSourceError,
    atlas_labels_path,
    atlas_volume_paths,
    canonicalize,
    downsample_volume,
    load_volumes,
)

STILL = SynthesisConfig(
    partial_volume_mm=(0.0, 0.0), bias=(0.0, 0.0), blur_mm=(0.0, 0.0), noise=(0.0, 0.0)
)
"""Synthesis without partial volume, bias, blur or noise: each voxel its label's value."""


def _brain_with_labels() -> tuple[Image, Image, Image]:
    """A 32^3 ellipsoid brain at 2 mm with three nested tissue labels and unlabelled voxels."""
    image, mask = ellipsoid_brain(32, 2.0, (24.0, 28.0, 20.0), seed=3, origin_mm=(-31.0,) * 3)
    grid = (np.indices((32, 32, 32)) - 15.5) * 2.0
    radius = np.sqrt((grid[0] / 24) ** 2 + (grid[1] / 28) ** 2 + (grid[2] / 20) ** 2)
    labels = np.select([radius < 0.4, radius < 0.7, radius < 1.0], [2, 1, 3], 0).astype(np.float32)
    labels[16, 16, 16] = 0  # a brain voxel without a label
    return image, mask, Image(torch.from_numpy(labels), image.affine.clone())


def _volume():
    image, mask, labels = _brain_with_labels()
    return canonicalize(image, mask, labels=labels)


def _label_means(image: torch.Tensor, labels: torch.Tensor) -> list[float]:
    return [float(image[labels == value].mean()) for value in (1, 2, 3)]


def test_a_seed_makes_the_same_brain_and_another_seed_another() -> None:
    volume = _volume()
    for mode in ("labels", "mixed"):
        config = SynthesisConfig(mode=mode)
        one = synthesize_volume(volume, config, torch.Generator().manual_seed(4))
        again = synthesize_volume(volume, config, torch.Generator().manual_seed(4))
        other = synthesize_volume(volume, config, torch.Generator().manual_seed(5))
        assert torch.equal(one.image.data, again.image.data), mode
        assert not torch.equal(one.image.data, other.image.data), mode


def test_the_labels_geometry_is_kept_and_their_intensities_redrawn() -> None:
    volume = _volume()
    means = []
    for seed in range(12):
        brain = synthesize_volume(volume, SynthesisConfig(), torch.Generator().manual_seed(seed))
        assert brain.mask is volume.mask and brain.labels is volume.labels
        assert torch.equal(brain.image.affine, volume.image.affine)
        assert torch.equal(brain.centre_mm, volume.centre_mm)
        assert bool((brain.image.data[~volume.mask] == 0).all())  # nothing outside the brain
        assert bool((brain.image.data[volume.mask] >= 0).all())
        inside = brain.image.data[volume.mask].double()
        assert float(torch.quantile(inside, 0.99)) == pytest.approx(1.0, abs=1e-4)
        means.append(_label_means(brain.image.data, volume.labels))
    assert len({tuple(round(m, 3) for m in row) for row in means}) == 12
    # The labels' order changes too: contrasts unlike any one atlas's.
    orders = {tuple(np.argsort(row)) for row in means}
    assert len(orders) > 1


def test_without_blur_noise_or_texture_each_label_is_one_level() -> None:
    volume = _volume()
    config = dataclasses.replace(STILL, texture=(0.0, 0.0))
    brain = synthesize_volume(volume, config, torch.Generator().manual_seed(0))
    for value in (1, 2, 3):
        inside = brain.image.data[volume.labels == value]
        assert float(inside.max() - inside.min()) < 1e-5, value
    # With texture, each label varies smoothly about its level.
    textured = dataclasses.replace(STILL, texture=(0.1, 0.1))
    brain = synthesize_volume(volume, textured, torch.Generator().manual_seed(0))
    for value in (1, 3):
        assert float(brain.image.data[volume.labels == value].std()) > 0.005, value


def test_a_monotone_remap_keeps_each_labels_intensity_order() -> None:
    image, mask, labels = _brain_with_labels()
    brain = mask.data[None] > 0.5
    real = torch.where(brain, image.data[None], torch.zeros(()))
    config = dataclasses.replace(STILL, mode="mixed", monotone_probability=1.0)
    made = synthesize(
        labels.data[None].long(),
        brain,
        image.affine,
        config,
        torch.Generator().manual_seed(2),
        image=real,
    )
    for value in (1, 2, 3):
        inside = labels.data[None] == value
        order = torch.argsort(real[inside])
        remapped = made.image[inside][order]
        assert bool((remapped[1:] >= remapped[:-1] - 1e-6).all()), value
    # A non-monotone remap does not keep it.
    free = dataclasses.replace(config, monotone_probability=0.0)
    made = synthesize(
        labels.data[None].long(), brain, image.affine, free, torch.Generator().manual_seed(2), real
    )
    inside = labels.data[None] == 1
    remapped = made.image[inside][torch.argsort(real[inside])]
    assert not bool((remapped[1:] >= remapped[:-1] - 1e-6).all())


def test_shapes_dtypes_and_a_batch_of_brains() -> None:
    image, mask, labels = _brain_with_labels()
    batch = labels.data[None].long().expand(2, -1, -1, -1).contiguous()
    brain = (mask.data[None] > 0.5).expand(2, -1, -1, -1)
    made = synthesize(batch, brain, image.affine, SynthesisConfig(), torch.Generator())
    assert made.image.shape == (2, 32, 32, 32) and made.image.dtype == torch.float32
    assert made.mask.dtype == torch.bool and torch.equal(made.mask, brain)
    assert made.labels.dtype == torch.int64 and torch.equal(made.labels, batch)
    assert not torch.equal(made.image[0], made.image[1])  # one draw per brain
    assert bool(torch.isfinite(made.image).all())
    with pytest.raises(ValueError, match="'mixed' mode needs the real 'image'"):
        synthesize(batch, brain, image.affine, SynthesisConfig(mode="mixed"), torch.Generator())
    with pytest.raises(ValueError, match="integers >= 0"):
        synthesize(batch.float(), brain, image.affine, SynthesisConfig(), torch.Generator())
    with pytest.raises(ValueError, match=r"\(B, I, J, K\) alike"):
        synthesize(batch[:, :4], brain, image.affine, SynthesisConfig(), torch.Generator())
    with pytest.raises(ValueError, match="no 'labels'"):
        synthesize_volume(canonicalize(image, mask), SynthesisConfig(), torch.Generator())


def test_a_deformed_brain_moves_its_mask_and_labels_together() -> None:
    volume = _volume()
    brain = synthesize_volume(
        volume, SynthesisConfig(deform_mm=4.0), torch.Generator().manual_seed(1)
    )
    assert brain.labels is not None
    assert not torch.equal(brain.mask, volume.mask)
    assert bool((brain.image.data[~brain.mask] == 0).all())
    # The labels follow the mask: nearly every labelled voxel is in the brain.
    assert float((brain.labels > 0)[~brain.mask].float().sum()) < 0.05 * float(brain.mask.sum())


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("mode", "synthseg"),
        ("mean_range", (0.5, 0.1)),
        ("noise", (-0.1, 0.1)),
        ("t2_levels", (0.5, 0.0)),
        ("t2_contrast", (0.0, 1.0)),
        ("t2_jitter", 1.0),
        ("t2_like_probability", 1.5),
        ("texture_mm", 0.0),
        ("bias_points", 1),
        ("curve_knots", 1.5),
        ("deform_mm", -1.0),
    ],
)
def test_bad_config_values_are_named(field: str, value: object) -> None:
    with pytest.raises(ConfigFieldError, match=f"SynthesisConfig: '{field}'"):
        SynthesisConfig(**{field: value})


def test_the_blur_is_scipys_gaussian_filter_per_brain() -> None:
    x = torch.rand(2, 1, 12, 14, 10, generator=torch.Generator().manual_seed(0))
    sigma = torch.tensor([[1.0, 0.0, 0.7], [0.5, 1.3, 0.0]])
    out = gaussian_blur(x, sigma)
    for i in range(2):
        expected = ndimage.gaussian_filter(
            x[i, 0].double().numpy(), sigma[i].tolist(), mode="constant", truncate=3.0
        )
        # Each brain's kernel has scipy's radius (3 standard deviations, rounded), normalised.
        np.testing.assert_allclose(out[i, 0].numpy(), expected, atol=1e-6)
    table = torch.tensor([[[0.0], [5.0], [7.0]]])
    labels = torch.tensor([[[[0, 1], [2, 1]]]])
    assert label_maps(labels, table).tolist() == [[[[[0.0, 5.0], [7.0, 5.0]]]]]


def test_warp_channels_reads_the_volume_at_x_plus_d() -> None:
    volume = _volume()
    data = volume.image.data[None]
    field = torch.zeros(3, 2, 2, 2, dtype=torch.float64)
    assert torch.allclose(warp_channels(data, volume.image.affine, field), data, atol=1e-5)
    field[0] = 2.0  # one voxel along i (the grid is 2 mm, axis-aligned)
    shifted = warp_channels(data, volume.image.affine, field)
    assert torch.allclose(shifted[0, :-1], data[0, 1:], atol=1e-5)


def test_canonical_volumes_carry_their_tissue_labels(tmp_path) -> None:
    image, mask, labels = _brain_with_labels()
    volume = canonicalize(image, mask, labels=labels)
    assert volume.labels is not None and volume.labels.dtype == torch.int16
    assert bool((volume.labels[~volume.mask] == 0).all())
    assert set(torch.unique(volume.labels).tolist()) == {0, 1, 2, 3}
    assert volume.to("cpu").labels is not None
    assert canonicalize(image, mask).labels is None
    half = Image(labels.data + 0.5, labels.affine)
    with pytest.raises(ValueError, match="not integers"):
        canonicalize(image, mask, labels=half)
    with pytest.raises(ValueError, match="labels and volume grids differ"):
        canonicalize(image, mask, labels=Image(labels.data[:8], labels.affine))
    # Coarsened: each block takes its most frequent label, none outside the mask.
    coarse = downsample_volume(volume, 2)
    assert coarse.labels is not None and coarse.labels.shape == coarse.mask.shape
    assert bool((coarse.labels[~coarse.mask] == 0).all())
    assert int(coarse.labels[8, 8, 8]) == 2 and int(coarse.labels[8, 8, 3]) == 3
    # Read from an atlas folder: the parcellation beside each volume.
    folder = tmp_path / "atlas" / "GA30"
    folder.mkdir(parents=True)
    save_nifti(image, folder / "srr.nii.gz")
    save_nifti(mask, folder / "mask.nii.gz")
    pairs = atlas_volume_paths(tmp_path / "atlas")
    with pytest.raises(VolumeSourceError, match=f"{ATLAS_LABELS} is missing"):
        load_volumes(pairs, labels=True)
    save_nifti(labels, folder / ATLAS_LABELS)
    assert atlas_labels_path(pairs[0][0]) == folder / ATLAS_LABELS
    (loaded,), _ = load_volumes(pairs, labels=True)
    assert loaded.labels is not None and torch.equal(loaded.labels, volume.labels)
    assert load_volumes(pairs)[0][0].labels is None
