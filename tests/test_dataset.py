"""Slice datasets: shapes, labels, empty-slice rule, determinism, workers, shifts, Euler grid."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.ndimage import gaussian_filter
from scipy.spatial.transform import Rotation
from torch.utils.data import DataLoader

from svr.image import Image
from svr.sampling.augment import SliceAugmentConfig, shift_poses
from svr.sampling.dataset import EulerGridDataset, EulerGridStream, SliceDatasetConfig, SliceStream
from svr.sampling.poses import EulerGridConfig, euler_grid_poses, pose_labels
from svr.sampling.slicer import SliceConfig, brain_fraction, sample_slices
from svr.sampling.volume import CanonicalVolume, canonicalize

SLICE = SliceConfig(size=(24, 20), spacing_mm=2.5)
LABEL_DIMS = {"se3": 6, "quat_translation": 7, "anchor_points": 9, "rotation6d_translation": 9}


def ellipsoid_volume(seed: int, semi_axes_mm=(27.0, 22.0, 18.0), n: int = 48) -> CanonicalVolume:
    """A ~48^3 1.5 mm volume: smooth random intensities inside an off-centre ellipsoid mask."""
    rng = np.random.default_rng(seed)
    spacing = 1.5
    affine = torch.diag(torch.tensor([spacing, spacing, spacing, 1.0], dtype=torch.float64))
    affine[:3, 3] = torch.tensor([-30.0, -40.0, -35.0], dtype=torch.float64)
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1) * spacing
    centre = np.array([n / 2 + 2, n / 2 - 3, n / 2 + 1]) * spacing
    inside = (((idx - centre) / np.array(semi_axes_mm)) ** 2).sum(-1) <= 1.0
    data = 1.0 + gaussian_filter(rng.normal(size=(n, n, n)), 2.0) * 5.0
    data = np.clip(data, 0.1, None) * inside
    volume = Image(torch.from_numpy(data).float(), affine)
    mask = Image(torch.from_numpy(inside.astype(np.float32)), affine)
    return canonicalize(volume, mask)


@pytest.fixture(scope="module")
def volumes() -> tuple[CanonicalVolume, CanonicalVolume]:
    return ellipsoid_volume(0), ellipsoid_volume(1, semi_axes_mm=(20.0, 25.0, 16.0))


def config(**changes) -> SliceDatasetConfig:
    base = SliceDatasetConfig(
        slice=SLICE, tz_range_mm=20.0, batch_size=6, num_batches=3, min_brain_fraction=0.2
    )
    return dataclasses.replace(base, **changes)


def batch_slice_config(batch: dict[str, torch.Tensor]) -> SliceConfig:
    thickness = float(batch["thickness_mm"][0])
    return dataclasses.replace(
        SLICE, spacing_mm=float(batch["spacing_mm"][0]), thickness_mm=thickness or None
    )


def assert_batches_equal(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for key in a:
        assert torch.equal(a[key], b[key]), key


@pytest.mark.parametrize("representation", list(LABEL_DIMS))
def test_batch_shapes_dtypes_and_labels(volumes, representation):
    stream = SliceStream(volumes, config(representation=representation, shift_mm=3.0))
    batches = list(stream)
    assert len(batches) == len(stream) == 3
    batch = batches[0]
    b, (h, w) = 6, SLICE.size
    assert batch["slices"].shape == (b, 1, h, w) and batch["slices"].dtype == torch.float32
    assert batch["labels"].shape == (b, LABEL_DIMS[representation])
    assert batch["labels"].dtype == torch.float32
    assert batch["poses"].shape == (b, 6) and batch["poses"].dtype == torch.float64
    assert batch["volume_index"].shape == (b,) and batch["volume_index"].dtype == torch.int64
    torch.testing.assert_close(batch["labels"], pose_labels(batch["poses"], representation).float())


def test_slices_are_sampled_at_the_returned_poses_with_the_batch_jitter(volumes):
    cfg = config(
        thickness_range_mm=(1.0, 4.0), spacing_range_mm=(2.0, 3.0), shift_mm=4.0, mix_volumes=True
    )
    spacings = set()
    for batch in SliceStream(volumes, cfg):
        slice_config = batch_slice_config(batch)
        spacings.add(slice_config.spacing_mm)
        assert 2.0 <= slice_config.spacing_mm <= 3.0
        assert 1.0 <= slice_config.thickness_mm <= 4.0
        for v, volume in enumerate(volumes):
            chosen = batch["volume_index"] == v
            expected = sample_slices(volume.image, batch["poses"][chosen], slice_config)
            torch.testing.assert_close(batch["slices"][chosen, 0], expected)
    assert len(spacings) == 3


def in_plane_offsets(poses: torch.Tensor) -> torch.Tensor:
    """(B,) norms of the translations' components within the slice plane, mm."""
    normal = torch.from_numpy(Rotation.from_rotvec(poses[:, :3].numpy()).as_matrix()[:, :, 2])
    t = poses[:, 3:]
    return (t - (t * normal).sum(1, keepdim=True) * normal).norm(dim=1)


def test_shifts_are_in_the_poses(volumes):
    plain = SliceStream(volumes, config(shift_mm=0.0, batch_size=32)).batch(0)
    shifted = SliceStream(volumes, config(shift_mm=4.0, batch_size=32)).batch(0)
    assert in_plane_offsets(plain["poses"]).max() < 1e-9
    offsets = in_plane_offsets(shifted["poses"])
    assert offsets.max() <= 4.0 * 2**0.5 + 1e-9
    assert offsets.min() > 0 and offsets.max() > 2.0


def test_an_integer_pixel_shift_translates_the_slice(volumes):
    volume, s = volumes[0], SLICE.spacing_mm
    poses = SliceStream(volumes, config()).batch(0)["poses"]
    rows, cols = 3, -2
    moved = shift_poses(poses, torch.tensor([[rows * s, cols * s]], dtype=torch.float64))
    original = sample_slices(volume.image, poses, SLICE)
    at_shifted = sample_slices(volume.image, moved, SLICE)
    h, w = SLICE.size
    # pixel (a, b) of the shifted slice is pixel (a + rows, b + cols) of the original
    torch.testing.assert_close(
        at_shifted[:, : h - rows, -cols:], original[:, rows:, : w + cols], atol=1e-5, rtol=1e-5
    )
    assert not torch.allclose(at_shifted, original, atol=1e-3)


def test_empty_slice_rule_holds(volumes):
    threshold = 0.35
    cfg = config(
        min_brain_fraction=threshold,
        spacing_range_mm=(2.0, 3.0),
        shift_mm=5.0,
        mix_volumes=True,
        rotation="uniform",
        batch_size=16,
    )
    fractions = []
    for batch in SliceStream(volumes, cfg):
        for v, volume in enumerate(volumes):
            chosen = batch["volume_index"] == v
            mask = Image(volume.mask.float(), volume.image.affine)
            slice_config = batch_slice_config(batch)
            fractions.append(brain_fraction(mask, batch["poses"][chosen], slice_config))
    assert torch.cat(fractions).min() >= threshold
    # the rule is active: without it, many of these poses would be rejected
    loose = SliceStream(volumes, dataclasses.replace(cfg, min_brain_fraction=0.0)).batch(0)
    mask = Image(volumes[0].mask.float(), volumes[0].image.affine)
    on_first = loose["volume_index"] == 0
    loose_fraction = brain_fraction(mask, loose["poses"][on_first], batch_slice_config(loose))
    assert (loose_fraction < threshold).any()


def test_impossible_rule_raises(volumes):
    stream = SliceStream(volumes, config(min_brain_fraction=1.0, max_resample_rounds=2))
    with pytest.raises(RuntimeError, match="min_brain_fraction"):
        stream.batch(0)


def test_same_seed_same_batches_different_seed_or_epoch_different(volumes):
    cfg = config(augment=SliceAugmentConfig(), shift_mm=2.0, mix_volumes=True)
    first, second = list(SliceStream(volumes, cfg)), list(SliceStream(volumes, cfg))
    for a, b in zip(first, second, strict=True):
        assert_batches_equal(a, b)
    assert not torch.equal(first[0]["poses"], first[1]["poses"])
    other = SliceStream(volumes, dataclasses.replace(cfg, seed=1)).batch(0)
    assert not torch.equal(other["poses"], first[0]["poses"])
    stream = SliceStream(volumes, cfg)
    stream.set_epoch(1)
    next_epoch = list(stream)
    assert not torch.equal(next_epoch[0]["poses"], first[0]["poses"])
    assert_batches_equal(next_epoch[2], stream.batch(2, epoch=1))
    with pytest.raises(ValueError, match="epoch"):
        stream.set_epoch(-1)
    with pytest.raises(ValueError, match="index"):
        stream.batch(-1)


def test_augmentation_draws_after_the_poses(volumes):
    plain = SliceStream(volumes, config()).batch(1)
    augmented = SliceStream(volumes, config(augment=SliceAugmentConfig(noise_prob=1.0))).batch(1)
    assert torch.equal(plain["poses"], augmented["poses"])
    assert not torch.equal(plain["slices"], augmented["slices"])


def test_dataloader_workers_give_distinct_reproducible_streams(volumes):
    cfg = config(num_batches=4, batch_size=4)
    stream = SliceStream(volumes, cfg)
    loaded = list(DataLoader(stream, batch_size=None, num_workers=2))
    assert len(loaded) == 4
    # worker w makes batches w, w + 2, ...: the same stream as without workers
    for index, batch in enumerate(loaded):
        assert_batches_equal(batch, stream.batch(index))
    assert not torch.equal(loaded[0]["poses"], loaded[1]["poses"])  # worker 0 vs worker 1


def test_endless_stream_has_no_length(volumes):
    stream = SliceStream(volumes, config(num_batches=None))
    with pytest.raises(TypeError):
        len(stream)
    iterator = iter(stream)
    batches = [next(iterator) for _ in range(4)]
    assert_batches_equal(batches[3], stream.batch(3))


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("slice", (24, 24)),
        ("thickness_range_mm", (4.0, 1.0)),
        ("spacing_range_mm", (0.0, 1.0)),
        ("rotation", "quaternion"),
        ("angle_range_deg", -1.0),
        ("tz_range_mm", float("inf")),
        ("shift_mm", -0.5),
        ("min_brain_fraction", 1.5),
        ("max_resample_rounds", 0),
        ("mix_volumes", 1),
        ("representation", "euler"),
        ("augment", {"noise_prob": 1.0}),
        ("batch_size", 0),
        ("num_batches", 0),
        ("seed", -3),
    ],
)
def test_bad_config_names_the_field(field, value):
    with pytest.raises(ValueError, match=field):
        SliceDatasetConfig(**{field: value})


def test_bad_volumes(volumes):
    with pytest.raises(ValueError, match="volumes"):
        SliceStream([], config())
    with pytest.raises(ValueError, match="volumes"):
        SliceStream([volumes[0].image], config())


GRID = EulerGridConfig(angle_step_deg=45.0, angle_range_deg=90.0, tz_step_mm=10.0, tz_range_mm=20.0)


@pytest.mark.parametrize("representation", ["se3", "anchor_points"])
def test_euler_grid_dataset_keeps_the_poses_that_pass_the_rule(volumes, representation):
    volume = volumes[0]
    dataset = EulerGridDataset(volume, GRID, SLICE, 0.2, representation, chunk_size=77)
    all_poses = euler_grid_poses(GRID)
    mask = Image(volume.mask.float(), volume.image.affine)
    kept = torch.nonzero(brain_fraction(mask, all_poses, SLICE) >= 0.2).flatten()
    assert 0 < len(dataset) == len(kept) < GRID.num_poses
    assert torch.equal(dataset.grid_indices, kept)
    assert torch.equal(dataset.poses, all_poses[kept])
    expected_slices = sample_slices(volume.image, all_poses[kept], SLICE)
    for i in (0, len(dataset) // 2, len(dataset) - 1):
        image, label = dataset[i]
        assert image.shape == (1, *SLICE.size) and image.dtype == torch.float32
        torch.testing.assert_close(image[0], expected_slices[i])
        torch.testing.assert_close(label, pose_labels(all_poses[kept[i]], representation).float())
    images, labels = next(iter(DataLoader(dataset, batch_size=5)))
    assert images.shape == (5, 1, *SLICE.size)
    assert labels.shape == (5, LABEL_DIMS[representation])
    torch.testing.assert_close(images[:, 0], expected_slices[:5])
    with pytest.raises(IndexError):
        dataset[len(dataset)]


def test_euler_grid_dataset_without_rule_keeps_everything(volumes):
    dataset = EulerGridDataset(volumes[0], GRID, SLICE, min_brain_fraction=0.0)
    assert len(dataset) == GRID.num_poses


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"min_brain_fraction": -0.1}, "min_brain_fraction"),
        ({"representation": "quat"}, "representation"),
        ({"chunk_size": 0}, "chunk_size"),
    ],
)
def test_euler_grid_dataset_bad_arguments(volumes, kwargs, field):
    with pytest.raises(ValueError, match=field):
        EulerGridDataset(volumes[0], GRID, SLICE, **kwargs)


def item_counts(volume_index: torch.Tensor, poses: torch.Tensor) -> dict[tuple, int]:
    """How often each (volume, pose) occurs (the grid repeats rotations at gimbal lock)."""
    keys = torch.cat([volume_index[:, None].double(), poses.round(decimals=6)], dim=1)
    rows, counts = keys.unique(dim=0, return_counts=True)
    return {tuple(r): int(c) for r, c in zip(rows.tolist(), counts.tolist(), strict=True)}


def test_euler_grid_stream_visits_every_kept_pose_once_per_pass(volumes):
    cfg = config(batch_size=7, num_batches=None, augment=SliceAugmentConfig())
    stream = EulerGridStream(volumes, cfg, GRID)
    per_volume = [EulerGridDataset(v, GRID, SLICE, cfg.min_brain_fraction) for v in volumes]
    assert torch.equal(stream.grid_poses, torch.cat([d.poses for d in per_volume]))
    n = len(stream.grid_poses)
    assert stream.batches_per_pass == n // 7 > 2
    batches = [stream.batch(i) for i in range(stream.batches_per_pass)]
    seen = item_counts(
        torch.cat([b["volume_index"] for b in batches]), torch.cat([b["poses"] for b in batches])
    )
    available = item_counts(stream.grid_volume_index, stream.grid_poses)
    assert sum(seen.values()) == 7 * (n // 7)
    assert all(count <= available.get(key, 0) for key, count in seen.items())  # none twice
    assert set(stream.batch(0)["volume_index"].tolist()) <= {0, 1}
    # The next pass is another permutation; batches are pure functions of (seed, epoch, index).
    assert not torch.equal(stream.batch(0)["poses"], stream.batch(stream.batches_per_pass)["poses"])
    fresh = EulerGridStream(volumes, cfg, GRID)
    for i in (stream.batches_per_pass + 1, 3, 0):
        assert_batches_equal(fresh.batch(i), stream.batch(i))
    assert not torch.equal(fresh.batch(0, epoch=1)["poses"], stream.batch(0)["poses"])


def test_euler_grid_stream_batches_are_cut_and_labelled_at_their_shifted_poses(volumes):
    cfg = config(batch_size=5, shift_mm=3.0, thickness_range_mm=(1.0, 3.0))
    stream = EulerGridStream(volumes, cfg, GRID)
    batch = stream.batch(4)
    in_plane = batch["poses"][:, None, :] - stream.grid_poses[None]
    assert not bool((in_plane.abs().amax(-1) < 1e-9).any())  # every pose shifted
    torch.testing.assert_close(batch["labels"], pose_labels(batch["poses"], "se3").float())
    for v in batch["volume_index"].unique().tolist():
        chosen = batch["volume_index"] == v
        expected = sample_slices(
            volumes[v].image, batch["poses"][chosen], batch_slice_config(batch)
        )
        torch.testing.assert_close(batch["slices"][chosen, 0], expected.float())


def test_euler_grid_stream_needs_a_full_batch(volumes):
    with pytest.raises(ValueError, match="fewer than batch_size=100000"):
        EulerGridStream(volumes[:1], config(batch_size=100000), GRID)
