"""Images in world space: a tensor plus its voxel-to-world affine, NIfTI I/O, world-point sampling.

Conventions (the documentation's conventions page, ``docs/conventions.md``):
    * An image is ``data`` (I, J, K) in NIfTI array order and a (4, 4) float64 ``affine`` mapping
      voxel indices ``(i, j, k)`` (voxel centres at integers) to world ``(x, y, z)`` in mm (RAS+).
    * :func:`world_to_grid` is the one place that maps world points to ``grid_sample``
      coordinates: it owns the ``(x, y, z) <-> (W, H, D)`` reordering and ``align_corners=True``
      (index ``0`` and ``n - 1`` map to -1 and +1); :func:`sample_grid` is the one place that calls
      ``grid_sample``, and :func:`sample_world` composes the two.
"""

from __future__ import annotations

import gzip
import logging
import os
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import nibabel as nib
import numpy as np
import torch
from scipy import ndimage
from torch import Tensor

from svr.files import atomic_write_bytes, check_output_path

NIFTI_SUFFIXES = (".nii", ".nii.gz")
DEFAULT_PERCENTILE = 99.0
"""Intensities are divided by this percentile of the brain's (the bright end to ~1)."""
GRID_ATOL_MM = 1e-3
"""Affines closer than this (mm, every entry) describe the same grid."""
_MIN_POINTS_PER_PART = 16384  # below this, splitting grid_sample over threads does not pay


log = logging.getLogger(__name__)


class ImageError(ValueError):
    """A file is not a usable image; the message names the file and the problem."""


@dataclass(frozen=True)
class Image:
    """A 3D image in world space.

    Attributes:
        data: (I, J, K) floating-point tensor, NIfTI array order.
        affine: (4, 4) float64 tensor, voxel index -> world mm, on the same device as ``data``.
    """

    data: Tensor
    affine: Tensor

    def __post_init__(self) -> None:
        if self.data.dim() != 3:
            raise ValueError(
                f"Image: 'data' must be 3D (I, J, K), got shape {tuple(self.data.shape)}"
            )
        if tuple(self.affine.shape) != (4, 4):
            raise ValueError(f"Image: 'affine' must be (4, 4), got {tuple(self.affine.shape)}")

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape (I, J, K)."""
        return tuple(self.data.shape)  # type: ignore[return-value]

    @property
    def spacing(self) -> Tensor:
        """(3,) voxel sizes in mm along the array axes (norms of the affine's columns)."""
        return self.affine[:3, :3].norm(dim=0)

    def to(
        self, device: torch.device | str | None = None, dtype: torch.dtype | None = None
    ) -> Image:
        """A copy on ``device`` with ``data`` in ``dtype`` (the affine stays float64)."""
        return Image(
            self.data.to(device=device, dtype=dtype),
            self.affine.to(device=device, dtype=torch.float64),
        )


def _fail(path: Path, problem: str) -> ImageError:
    return ImageError(f"{path}: {problem}")


@contextmanager
def _nibabel_messages(path: Path) -> Iterator[None]:
    """Hold back nibabel's header messages, which it prints to stderr by its own handler.

    A file that loads after all gets them as warnings of this module, naming the file; one that
    does not is reported by the error alone (which says the same).
    """
    messages: list[str] = []

    class Collect(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            messages.append(record.getMessage())

    logger = nib.imageglobals.logger
    saved = logger.handlers, logger.propagate
    logger.handlers, logger.propagate = [Collect()], False
    try:
        yield
    finally:
        logger.handlers, logger.propagate = saved
    for message in messages:
        log.warning("%s: %s", path, message)


def load_nifti(path: str | os.PathLike[str], dtype: torch.dtype = torch.float32) -> Image:
    """Load a 3D NIfTI image with its world affine (sform, else qform, as nibabel chooses).

    A trailing 4th dimension of size 1 is dropped.

    Args:
        path: A ``.nii`` or ``.nii.gz`` file.
        dtype: Floating dtype of the returned data.

    Returns:
        The image, on the CPU.

    Raises:
        ImageError: Naming the file, if it is missing, unreadable, not NIfTI, truncated or
            corrupted, not real-valued (complex, RGB), not 3D, empty, has non-finite voxels, or a
            singular or non-finite affine.
    """
    p = Path(path)
    if not p.exists():
        raise _fail(p, "no such file")
    if not p.is_file():
        raise _fail(p, "not a file")
    if not str(p).endswith(NIFTI_SUFFIXES):
        raise _fail(p, "not a NIfTI file name (expected .nii or .nii.gz)")
    if not os.access(p, os.R_OK):
        raise _fail(p, "permission denied")
    try:
        # singular affines are reported below
        with np.errstate(invalid="ignore", divide="ignore"), _nibabel_messages(p):
            # a NIfTI file loads as a spatial image (Nifti1Image, Nifti2Image)
            img = cast("nib.spatialimages.SpatialImage", nib.load(str(p)))
            stored = img.get_data_dtype()
            if stored.kind not in "biuf":  # complex would lose its imaginary part, RGB fail
                raise _fail(p, f"unsupported data type {stored} (expected real-valued voxels)")
            array = np.asarray(img.dataobj, dtype=np.float64)
            affine = np.asarray(img.affine, dtype=np.float64)
    except PermissionError as err:
        raise _fail(p, "permission denied") from err
    except ImageError:
        raise
    except (
        OSError,
        EOFError,
        ValueError,
        zlib.error,  # a corrupted deflate stream in a .nii.gz
        nib.filebasedimages.ImageFileError,
        nib.spatialimages.HeaderDataError,  # e.g. an unknown data type code
    ) as err:
        detail = " ".join(str(err).split())
        raise _fail(p, f"cannot read as NIfTI ({err.__class__.__name__}: {detail})") from err
    if array.size == 0:
        raise _fail(p, f"image is empty (shape {array.shape})")
    if array.ndim == 4 and array.shape[3] == 1:
        array = array[..., 0]
    if array.ndim != 3:
        raise _fail(p, f"expected a 3D image, got {array.ndim}D with shape {array.shape}")
    if not np.isfinite(array).all():
        raise _fail(p, f"{int((~np.isfinite(array)).sum())} voxels are NaN or Inf")
    if not np.isfinite(affine).all() or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise _fail(p, "the affine (sform/qform) is singular or not finite")
    return Image(torch.from_numpy(array).to(dtype), torch.from_numpy(affine))


def save_nifti(
    image: Image, path: str | os.PathLike[str], overwrite: bool = False, description: str = ""
) -> Path:
    """Write an image as float32 NIfTI with sform and qform set to its affine, atomically.

    Args:
        image: The image (any device).
        path: A ``.nii`` or ``.nii.gz`` file name.
        overwrite: Whether an existing file may be replaced.
        description: The header's ``descrip`` text (at most 80 ASCII characters; e.g.
            :func:`svr.stamp.verdict_stamp`).

    Returns:
        The written path.

    Raises:
        ImageError: If the name does not end in .nii or .nii.gz.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    p = check_output_path(path, overwrite)
    if not str(p).endswith(NIFTI_SUFFIXES):
        raise _fail(p, "output must end in .nii or .nii.gz")
    affine = image.affine.detach().cpu().numpy()
    nii = nib.Nifti1Image(image.data.detach().cpu().numpy().astype(np.float32), affine)
    nii.set_sform(affine, code=1)
    nii.set_qform(affine, code=1)
    if description:
        if len(description) > 80 or not description.isascii():
            raise ValueError(
                f"{p}: a NIfTI description holds 80 ASCII characters, got {description!r}"
            )
        nii.header["descrip"] = description.encode("ascii")
    return _save_atomically(nii, p)


def save_mask_like(
    mask: Tensor | np.ndarray,
    reference: str | os.PathLike[str],
    path: str | os.PathLike[str],
    overwrite: bool = False,
) -> Path:
    """Write a uint8 mask (1 inside, 0 outside) on a NIfTI file's grid with its header, atomically.

    As :func:`save_labels_like`, with every nonzero value written as 1.

    Args:
        mask: (I, J, K) mask (nonzero = inside) on the reference's grid.
        reference: The NIfTI file whose grid and header the mask takes (e.g. the stack).
        path: A ``.nii`` or ``.nii.gz`` file name.
        overwrite: Whether an existing file may be replaced.

    Returns:
        The written path.

    Raises:
        ImageError: As :func:`save_labels_like`.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    data = np.asarray(mask.detach().cpu().numpy() if isinstance(mask, Tensor) else mask)
    return _save_uint8_like(data != 0, reference, path, overwrite, "mask")


def save_labels_like(
    labels: Tensor | np.ndarray,
    reference: str | os.PathLike[str],
    path: str | os.PathLike[str],
    overwrite: bool = False,
) -> Path:
    """Write a uint8 label map on a NIfTI file's grid with that file's header, atomically.

    The reference's header is copied, so the map's sform and qform (matrices and codes), voxel
    sizes and units equal the reference's exactly (a trailing 4th dimension of size 1 is dropped,
    as :func:`load_nifti` drops it); the data type becomes uint8 without scaling.

    Args:
        labels: (I, J, K) integer labels in 0..255 on the reference's grid.
        reference: The NIfTI file whose grid and header the map takes (e.g. the volume).
        path: A ``.nii`` or ``.nii.gz`` file name.
        overwrite: Whether an existing file may be replaced.

    Returns:
        The written path.

    Raises:
        ImageError: If the name does not end in .nii or .nii.gz, the reference cannot be read,
            the map's shape is not the reference's (3D part) or a label is outside 0..255.
        OutputExistsError: If the file exists and ``overwrite`` is false.
    """
    return _save_uint8_like(labels, reference, path, overwrite, "label map")


def _save_uint8_like(
    labels: Tensor | np.ndarray,
    reference: str | os.PathLike[str],
    path: str | os.PathLike[str],
    overwrite: bool,
    what: str,
) -> Path:
    """:func:`save_labels_like`, its errors naming the data ``what``."""
    p = check_output_path(path, overwrite)
    if not str(p).endswith(NIFTI_SUFFIXES):
        raise _fail(p, "output must end in .nii or .nii.gz")
    ref = Path(reference)
    try:
        with _nibabel_messages(ref):
            source = cast("nib.Nifti1Image", nib.load(str(ref)))  # NIfTI-1 or -2
    except (OSError, ValueError, nib.filebasedimages.ImageFileError) as err:
        raise _fail(ref, f"cannot read as NIfTI ({' '.join(str(err).split())})") from err
    data = np.asarray(labels.detach().cpu().numpy() if isinstance(labels, Tensor) else labels)
    shape = tuple(source.shape[:3])
    if data.shape != shape:
        raise _fail(p, f"{what} shape {data.shape} is not the grid of {ref} {shape}")
    if data.size and (data.min() < 0 or data.max() > 255):
        raise _fail(p, f"labels must be in 0..255, got {data.min()}..{data.max()}")
    header = source.header.copy()
    header.set_data_dtype(np.uint8)
    header.set_slope_inter(1.0, 0.0)
    # Without an affine, nibabel keeps the copied header's sform and qform fields as stored
    # (nothing is recomputed from a matrix, so quaternions and offsets stay bit for bit).
    return _save_atomically(nib.Nifti1Image(data.astype(np.uint8), None, header), p)


def _save_atomically(image: nib.Nifti1Image, path: Path) -> Path:
    """Write ``image`` with :func:`svr.files.atomic_write_bytes` (gzip for ``.nii.gz``)."""
    data = image.to_bytes()
    if path.name.endswith(".gz"):
        data = gzip.compress(data, compresslevel=6)
    return atomic_write_bytes(path, data, overwrite=True)


def voxel_to_world(affine: Tensor, voxels: Tensor) -> Tensor:
    """Map continuous voxel indices to world points (mm) of an image with ``affine``.

    Args:
        affine: (4, 4) voxel -> world affine.
        voxels: (..., 3) voxel indices ``(i, j, k)`` (voxel centres at integers).

    Returns:
        (..., 3) world points in mm, in ``voxels``' dtype and device.
    """
    a = affine.to(device=voxels.device, dtype=voxels.dtype)
    return voxels @ a[:3, :3].T + a[:3, 3]


def voxel_centres(image: Image, dtype: torch.dtype = torch.float64) -> Tensor:
    """World positions of every voxel centre of ``image``.

    Args:
        image: The image (its grid: shape and affine).
        dtype: dtype of the result (computed in it).

    Returns:
        (I, J, K, 3) world points in mm, on the image's device.
    """
    device = image.data.device
    axes = [torch.arange(n, dtype=dtype, device=device) for n in image.shape]
    return voxel_to_world(image.affine, torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1))


def stack_slice_poses(stack: Image) -> Tensor:
    """Poses of a stack's k-planes in its world frame (slice convention of ``docs/conventions.md``).

    The rotation's columns are the unit in-plane directions ``u`` (array axis 0) and ``v`` (array
    axis 1, orthogonalised against ``u`` if the affine is sheared) and the normal ``u x v``; the
    translation is the world position of the plane centre, voxel ``((I - 1) / 2, (J - 1) / 2, k)``.

    Args:
        stack: An ``(I, J, K)`` image.

    Returns:
        (K, 4, 4) float64 poses (slice plane, mm -> world, mm) on the affine's device.
    """
    affine = stack.affine.to(torch.float64)
    e_u = affine[:3, 0] / affine[:3, 0].norm()
    e_v = affine[:3, 1] - (e_u @ affine[:3, 1]) * e_u
    e_v = e_v / e_v.norm()
    i, j, k = stack.shape
    centres = torch.zeros(k, 3, dtype=torch.float64, device=affine.device)
    centres[:, 0], centres[:, 1] = (i - 1) / 2, (j - 1) / 2
    centres[:, 2] = torch.arange(k, dtype=torch.float64, device=affine.device)
    poses = torch.eye(4, dtype=torch.float64, device=affine.device).repeat(k, 1, 1)
    poses[:, :3, :3] = torch.stack([e_u, e_v, torch.linalg.cross(e_u, e_v)], dim=1)
    poses[:, :3, 3] = voxel_to_world(affine, centres)
    return poses


def world_to_voxel(affine: Tensor, points: Tensor) -> Tensor:
    """Map world points (mm) to continuous voxel indices of an image with ``affine``.

    Args:
        affine: (4, 4) voxel -> world affine.
        points: (..., 3) world points in mm.

    Returns:
        (..., 3) voxel indices ``(i, j, k)`` in ``points``' dtype.
    """
    inv = torch.linalg.inv(affine.to(torch.float64)).to(device=points.device, dtype=points.dtype)
    return points @ inv[:3, :3].T + inv[:3, 3]


def world_to_grid(image: Image) -> Tensor:
    """(3, 4) float64 affine from world mm to ``grid_sample`` coordinates of ``image``.

    ``grid_sample`` reads the data (I, J, K) as (D, H, W), so grid ``x`` indexes ``k``, ``y``
    indexes ``j`` and ``z`` indexes ``i``; with ``align_corners=True`` index 0 and ``n - 1`` map to
    -1 and +1 (a size-1 axis maps index 0 to -1).
    """
    inv = torch.linalg.inv(image.affine.to(torch.float64))[:3]
    sizes = torch.tensor(
        [max(n - 1, 1) for n in image.shape], dtype=torch.float64, device=inv.device
    )
    to_grid = (2.0 / sizes)[:, None] * inv
    to_grid[:, 3] -= 1.0
    return to_grid.flip(0)


def sample_grid(image: Image, grid: Tensor, mode: str = "bilinear") -> Tensor:
    """Sample an image at ``grid_sample`` coordinates (from :func:`world_to_grid`); zero outside.

    Args:
        image: The image.
        grid: (..., 3) normalised coordinates ``(x, y, z)``, on ``image``'s device.
        mode: ``"bilinear"`` (trilinear in 3D) or ``"nearest"``.

    Returns:
        (...) sampled values in the dtype of ``image.data``.
    """
    return sample_channels(image.data[None], grid, mode)[0]


def sample_channels(data: Tensor, grid: Tensor, mode: str = "bilinear") -> Tensor:
    """Sample a multi-channel volume at ``grid_sample`` coordinates; zero outside.

    The one place that calls ``grid_sample``. On the CPU, ``grid_sample`` parallelises only over
    its batch dimension, so the points are split into one batch per thread over a zero-copy
    expansion of the volume.

    Args:
        data: (C, I, J, K) channels on one grid (NIfTI array order).
        grid: (..., 3) normalised coordinates ``(x, y, z)`` of that grid, on ``data``'s device.
        mode: ``"bilinear"`` (trilinear in 3D) or ``"nearest"``.

    Returns:
        (C, ...) sampled values in the dtype of ``data``.
    """
    flat = grid.reshape(-1, 3).to(data.dtype)
    count = flat.shape[0]
    channels = data.shape[0]
    parts = torch.get_num_threads() if data.device.type == "cpu" else 1
    parts = max(1, min(parts, count // _MIN_POINTS_PER_PART))
    per_part = -(-count // parts)
    if per_part * parts != count:
        flat = torch.cat([flat, flat.new_full((per_part * parts - count, 3), 2.0)])
    volume = data[None].expand(parts, *data.shape)
    out = torch.nn.functional.grid_sample(
        volume,
        flat.reshape(parts, 1, 1, per_part, 3),
        mode=mode,
        padding_mode="zeros",
        align_corners=True,
    )  # (parts, C, 1, 1, per_part)
    out = out.reshape(parts, channels, per_part).transpose(0, 1).reshape(channels, -1)
    return out[:, :count].reshape(channels, *grid.shape[:-1])


def sample_world(image: Image, points: Tensor, mode: str = "bilinear") -> Tensor:
    """Sample an image at world points; zero outside the image.

    Args:
        image: The image.
        points: (..., 3) world points in mm, on ``image``'s device (computed in the image's dtype).
        mode: ``"bilinear"`` (trilinear in 3D) or ``"nearest"``.

    Returns:
        (...) sampled values in the dtype of ``image.data``.
    """
    if points.shape[-1] != 3:
        raise ValueError(
            f"sample_world(): 'points' must have shape (..., 3), got {tuple(points.shape)}"
        )
    m = world_to_grid(image).to(device=points.device, dtype=image.data.dtype)
    flat = points.reshape(-1, 3).to(image.data.dtype)
    return sample_grid(image, torch.addmm(m[:, 3], flat, m[:, :3].T), mode).reshape(
        points.shape[:-1]
    )


def resample_to_grid(image: Image, like: Image, mode: str = "bilinear") -> Image:
    """Resample ``image`` by world position onto the grid of ``like``; 0 outside ``image``.

    Args:
        image: The image to resample; its world frame must be ``like``'s.
        like: The image whose grid (shape and affine) the result has.
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.

    Returns:
        A float32 image on ``like``'s grid and device (affine in float64).
    """
    device = like.data.device
    points = voxel_centres(like.to(device))
    data = sample_world(image.to(device, torch.float32), points.float(), mode)
    return Image(data, like.affine.to(device, torch.float64).clone())


def same_grid(a: Image, b: Image, atol_mm: float = GRID_ATOL_MM) -> bool:
    """Whether two images share a grid: the same shape and affines within ``atol_mm``."""
    return a.shape == b.shape and torch.allclose(
        a.affine.to(b.affine), b.affine, atol=atol_mm, rtol=0
    )


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest connected component of a bool array (face connectivity), or ``mask`` if empty.

    Args:
        mask: Bool array, 2D or 3D.

    Returns:
        Bool array of the same shape.
    """
    labels, count = ndimage.label(mask)
    if count == 0:
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(sizes.argmax())


def mask_on_grid(mask: Image, like: Image) -> Tensor:
    """A mask (voxels > 0.5) as a bool tensor on ``like``'s grid, resampled (nearest) if needed.

    Args:
        mask: The mask, on any grid in ``like``'s world frame.
        like: The image whose grid the result is on.

    Returns:
        (I, J, K) bool tensor on ``like``'s device.
    """
    if same_grid(mask, like):
        return (mask.data > 0.5).to(like.data.device)
    log.debug("the mask's grid differs from the image's; resampling it")
    return resample_to_grid(mask, like, mode="nearest").data > 0.5


def intensity_scale(values: Tensor, name: str, percentile: float = DEFAULT_PERCENTILE) -> float:
    """The ``percentile``-th percentile of ``values`` (in float64), checked to be positive.

    The divisor that normalises a stack's intensities (the brain's bright end to ~1).

    Args:
        values: Voxel values (any shape), e.g. those inside the brain mask.
        name: What they come from, for the error message.
        percentile: In (0, 100].

    Returns:
        The percentile.

    Raises:
        ValueError: Naming ``name``, if ``values`` is empty or the percentile is not positive.
    """
    if values.numel() == 0:
        raise ValueError(f"{name}: all voxels are zero")
    scale = float(np.percentile(values.detach().cpu().double().numpy(), percentile))
    if not scale > 0:
        raise ValueError(
            f"{name}: the {percentile:g}th percentile of the intensities is {scale}; "
            "expected a positive value"
        )
    return scale
