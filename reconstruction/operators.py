"""The slice acquisition model and its adjoint: volume -> slices through a Gaussian PSF.

An observed slice pixel ``p`` of slice ``i`` is modelled as the volume integrated against a
3D Gaussian PSF centred at the pixel's world position ``T_i (u_p, v_p, 0)``: in-plane standard
deviation ``sigma_in = 1.2067 * spacing / 2.3548`` and through-plane ``sigma_t = thickness /
2.3548`` (NeSVoR's and SVRTK's Gaussian PSF). A Gaussian with different in-plane and
through-plane widths is an isotropic Gaussian of ``sigma_in`` convolved with a 1D Gaussian of
``sqrt(sigma_t**2 - sigma_in**2)`` along the slice normal, so the forward operator is

    A x = S(B x),

``B`` a separable isotropic Gaussian blur of the volume (one ``sigma_in`` for all slices: the
smallest, so stacks with coarser in-plane spacing are modelled slightly sharp) and ``S`` the sum
over Gauss-Hermite nodes along each slice's normal of trilinear samples of the blurred volume.
``B`` is symmetric and ``S``'s adjoint is the exact transpose of trilinear interpolation
(``grid_sample``'s gradient), so :meth:`SliceProjector.adjoint` is the exact adjoint of
:meth:`SliceProjector.forward` (tested by the dot-product test).

Frames: poses map slice-plane mm to the frame of the volume grid's affine (scanner or canonical).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np
import torch
from torch import Tensor

from svr.image import Image, sample_grid, world_to_grid
from svr.reconstruction.slices import SliceSet
from svr.sampling.slicer import FWHM_TO_SIGMA, IN_PLANE_PSF_FWHM

__all__ = [
    "SliceProjector",
    "VolumeGrid",
    "gaussian_blur",
    "psf_nodes",
]


@dataclass(frozen=True)
class VolumeGrid:
    """The voxel grid of a volume being reconstructed.

    Attributes:
        shape: (I, J, K) voxels.
        affine: (4, 4) float64 voxel -> frame mm.
    """

    shape: tuple[int, int, int]
    affine: Tensor

    @property
    def spacing(self) -> Tensor:
        """(3,) voxel sizes in mm."""
        return self.affine[:3, :3].norm(dim=0)

    def image(self, data: Tensor) -> Image:
        """``data`` (I, J, K) on this grid as an :class:`Image`."""
        return Image(data, self.affine.to(data.device))


def psf_nodes(samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Gauss-Hermite nodes (in standard deviations) and weights (summing to 1) of a Gaussian."""
    if samples < 1 or samples % 2 == 0:
        raise ValueError(f"psf_nodes(): 'samples' must be an odd integer >= 1, got {samples}")
    nodes, weights = np.polynomial.hermite_e.hermegauss(samples)
    return nodes, weights / weights.sum()


def _gaussian_kernel(sigma: float, dtype: torch.dtype, device: torch.device) -> Tensor:
    radius = max(1, math.ceil(3.0 * sigma))
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    k = torch.exp(-0.5 * (x / sigma) ** 2)
    return (k / k.sum()).to(device=device, dtype=dtype)


def gaussian_blur(volume: Tensor, sigma_vox: tuple[float, float, float]) -> Tensor:
    """Separable Gaussian blur with zero padding (a symmetric, hence self-adjoint, operator).

    Args:
        volume: (I, J, K) tensor.
        sigma_vox: Standard deviation along each axis in voxels (0 leaves the axis alone).

    Returns:
        (I, J, K) blurred tensor.
    """
    out = volume[None, None]
    for axis, sigma in enumerate(sigma_vox):
        if sigma <= 0:
            continue
        k = _gaussian_kernel(float(sigma), volume.dtype, volume.device)
        shape = [1, 1, 1, 1, 1]
        shape[2 + axis] = len(k)
        padding = [0, 0, 0]
        padding[axis] = len(k) // 2
        out = torch.nn.functional.conv3d(out, k.reshape(shape), padding=tuple(padding))
    return out[0, 0]


class SliceProjector:
    """Forward (volume -> slice pixels) and adjoint operators for the masked pixels of a slice set.

    Only pixels inside the slice masks are modelled; they are held as one flat list (``P``
    pixels) with the index of their slice, so every operator is a single batched call.

    Args:
        grid: The volume's grid.
        slices: The slices (their masks, spacing and thickness are used; poses are arguments).
        psf_samples: Gauss-Hermite nodes along the normal (odd; 1 samples the plane only).
        in_plane_psf: Include the in-plane PSF (the isotropic blur ``B``).
        pixels: (N, H, W) bool, the pixels to model; default ``slices.masks``.
    """

    def __init__(
        self,
        grid: VolumeGrid,
        slices: SliceSet,
        psf_samples: int = 5,
        in_plane_psf: bool = True,
        pixels: Tensor | None = None,
    ) -> None:
        self.grid = grid
        self.num_slices = len(slices)
        self.size = slices.size
        self.pixel_mm = float(slices.spacing_mm.min())
        device = slices.device
        if pixels is not None and tuple(pixels.shape) != tuple(slices.masks.shape):
            raise ValueError(
                f"SliceProjector: 'pixels' must have shape {tuple(slices.masks.shape)}, "
                f"got {tuple(pixels.shape)}"
            )
        index = torch.nonzero(slices.masks if pixels is None else pixels)  # (P, 3): slice, a, b
        self.slice_of = index[:, 0]
        self.pixel_of = index[:, 1] * self.size[1] + index[:, 2]
        h, w = self.size
        spacing = slices.spacing_mm.to(torch.float64)[self.slice_of]
        self.uv_mm = torch.stack(
            [
                (index[:, 1] - (h - 1) / 2) * spacing[:, 0],
                (index[:, 2] - (w - 1) / 2) * spacing[:, 1],
            ],
            dim=-1,
        ).float()
        sigma_in = (
            float(IN_PLANE_PSF_FWHM * FWHM_TO_SIGMA * slices.spacing_mm.min())
            if in_plane_psf
            else 0.0
        )
        self.blur_sigma_vox = cast(
            "tuple[float, float, float]",
            tuple(float(sigma_in / s) for s in grid.spacing.tolist()),
        )
        sigma_t = slices.thickness_mm.to(torch.float64) * FWHM_TO_SIGMA
        sigma_normal = torch.sqrt(torch.clamp(sigma_t**2 - sigma_in**2, min=0.0))
        nodes, weights = psf_nodes(psf_samples)
        # (N, K) offsets along each slice's normal in mm, (K,) weights.
        self.normal_offsets_mm = sigma_normal[:, None] * torch.as_tensor(nodes, device=device)
        self.weights = torch.as_tensor(weights, dtype=torch.float32, device=device)
        self.to_grid = world_to_grid(grid.image(torch.zeros(1).expand(grid.shape))).to(device)

    @property
    def num_pixels(self) -> int:
        """P, the number of modelled (masked) pixels."""
        return int(self.slice_of.shape[0])

    def gather(self, images: Tensor) -> Tensor:
        """(N, H, W) images -> (P,) values at the modelled pixels."""
        return images.reshape(self.num_slices, -1)[self.slice_of, self.pixel_of]

    def slice_sums(self, values: Tensor) -> Tensor:
        """(P,) or (P, C) values -> (N,) or (N, C) sums per slice (differentiable)."""
        out = values.new_zeros((self.num_slices, *values.shape[1:]))
        return out.index_add(0, self.slice_of, values)

    def world_points(self, poses: Tensor, pixels: Tensor | None = None) -> Tensor:
        """Frame coordinates (mm) of every PSF node of every modelled pixel.

        Per-slice axes and PSF node positions are composed in float64, the per-pixel sums in
        float32 (1e-5 mm at 100 mm from the origin).

        Args:
            poses: (N, 4, 4) slice poses (may require grad: the result is differentiable).
            pixels: Indices into the ``P`` pixels to use (coarse levels), or ``None`` for all.

        Returns:
            (K, P', 3) float32 points.
        """
        T = poses.to(torch.float64)
        R = T[:, :3, :3]
        nodes = (T[:, None, :3, 3] + self.normal_offsets_mm[..., None] * R[:, None, :, 2]).float()
        axis_u, axis_v = R[:, :, 0].float(), R[:, :, 1].float()
        sid, uv = self.slice_of, self.uv_mm
        if pixels is not None:
            sid, uv = sid[pixels], uv[pixels]
        centre = uv[:, :1] * axis_u[sid] + uv[:, 1:] * axis_v[sid]  # (P, 3)
        return nodes[sid].transpose(0, 1) + centre[None]

    def to_grid_coordinates(self, points: Tensor) -> Tensor:
        """(..., 3) frame mm -> float32 ``grid_sample`` coordinates of the grid."""
        M = self.to_grid.to(device=points.device, dtype=torch.float32)
        return torch.addmm(M[:, 3], points.reshape(-1, 3).float(), M[:, :3].T).reshape(points.shape)

    def grid_points(self, poses: Tensor, pixels: Tensor | None = None) -> Tensor:
        """``grid_sample`` coordinates of :meth:`world_points`, (K, P', 3) float32."""
        return self.to_grid_coordinates(self.world_points(poses, pixels))

    def sample(self, blurred: Tensor, points: Tensor) -> Tensor:
        """PSF-weighted samples of a blurred (I, J, K) volume at (K, P', 3) points -> (P',)."""
        values = sample_grid(self.grid.image(blurred), points)
        return self.weights.to(values) @ values

    def blur(self, volume: Tensor) -> Tensor:
        """``B x``: the in-plane PSF as an isotropic blur of the (I, J, K) volume."""
        return gaussian_blur(volume, self.blur_sigma_vox)

    def forward(self, volume: Tensor, points: Tensor) -> Tensor:
        """``A x``: (P',) pixel values simulated from an (I, J, K) volume at :meth:`grid_points`."""
        return self.sample(self.blur(volume), points)

    def spread(self, values: Tensor, points: Tensor) -> Tensor:
        """``S^T y``: (P',) values spread onto the (I, J, K) grid, without the in-plane blur.

        The adjoint of :meth:`sample`; :meth:`adjoint` is ``B`` applied to it.
        """
        with torch.enable_grad():
            x = torch.zeros(
                self.grid.shape, dtype=values.dtype, device=values.device, requires_grad=True
            )
            (spread,) = torch.autograd.grad(self.sample(x, points), x, grad_outputs=values)
        return spread

    def adjoint(self, values: Tensor, points: Tensor) -> Tensor:
        """``A^T y``: (P',) pixel values spread back onto the (I, J, K) grid."""
        return self.blur(self.spread(values, points))
