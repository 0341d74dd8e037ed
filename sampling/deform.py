"""Random smooth non-rigid deformations of a canonical volume (anatomy the atlas does not have).

A deformation is a world-frame displacement field ``d`` in mm on a coarse ``c x c x c`` control
grid that spans the volume's voxel grid corner to corner (array order ``I, J, K``); between control
points it is trilinear. A deformed volume reads the original at ``x + d(x)``:
``J(x) = I(x + d(x))`` (:func:`svr.sampling.slicer.sample_slices` with ``displacement_mm``).

:func:`random_displacement` draws the control values as independent Gaussians of standard deviation
``std_mm`` per component, then removes their least-squares *rigid* part (a translation ``t`` and a
small rotation ``w x x`` about the canonical origin). What is left moves no landmark on average and
turns nothing on average, so a slice's pose label stays the pose in the canonical frame of the
deformed brain: the deformation changes the anatomy, not the frame.
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional

from svr.geometry import hat
from svr.image import Image, sample_channels, voxel_centres, voxel_to_world, world_to_grid
from svr.validation import is_finite_number, is_integer

DEFAULT_CONTROL_POINTS = 5
"""Control points per axis: about 27-38 mm apart over the atlas volumes (108-151 mm across)."""


def control_point_positions(image: Image, control_points: int) -> Tensor:
    """World positions of the control grid over ``image``'s voxel grid.

    Args:
        image: The volume (its affine maps voxel indices to world mm).
        control_points: Points per axis, >= 2; the first and last sit on the corner voxels.

    Returns:
        (c, c, c, 3) float64 world positions in mm, on the image's device, array order.
    """
    affine = image.affine.to(torch.float64)
    axes = [
        torch.linspace(0.0, float(n - 1), control_points, dtype=torch.float64, device=affine.device)
        for n in image.shape
    ]
    return voxel_to_world(affine, torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1))


def remove_rigid_part(displacement_mm: Tensor, positions_mm: Tensor) -> Tensor:
    """Subtract the least-squares translation and infinitesimal rotation from a displacement field.

    Fits ``d(x) ~ t + w x x`` (linearised rigid motion about the world origin) to the control
    values and returns ``d - (t + w x x)``.

    Args:
        displacement_mm: (N, 3) displacements in mm, world frame.
        positions_mm: (N, 3) positions of the control points in mm, world frame.

    Returns:
        (N, 3) float64 displacements with no rigid part: their mean is 0 and so is
        ``sum_i x_i x d_i`` about the centroid.
    """
    x = positions_mm.to(torch.float64)
    d = displacement_mm.to(torch.float64)
    n = len(x)
    skew = -hat(x)  # (N, 3, 3): w x x = -(x x w), so d_k = t_k + (skew @ w)_k
    eye = torch.eye(3, dtype=torch.float64, device=x.device).expand(n, 3, 3)
    design = torch.cat([eye, skew], dim=2).reshape(3 * n, 6)
    # Normal equations (6 x 6, well conditioned for a spread-out grid): bit-reproducible.
    params = torch.linalg.solve(design.T @ design, design.T @ d.reshape(3 * n, 1))
    return d - (design @ params).reshape(n, 3)


def random_displacement(
    image: Image,
    std_mm: float,
    generator: torch.Generator,
    control_points: int = DEFAULT_CONTROL_POINTS,
) -> Tensor:
    """A random smooth displacement field over ``image``, with no rigid part (module docstring).

    Args:
        image: The volume to deform (canonical frame).
        std_mm: Standard deviation of each control value's components before the rigid part is
            removed, mm, >= 0.
        generator: The only source of randomness (CPU generator).
        control_points: Control points per axis, >= 2.

    Returns:
        (3, c, c, c) float64 world-frame displacements in mm, on the image's device, for
        :func:`svr.sampling.slicer.sample_slices`'s ``displacement_mm``.

    Raises:
        ValueError: Naming the argument, if ``std_mm`` or ``control_points`` is invalid.
    """
    if not (is_finite_number(std_mm) and std_mm >= 0):
        raise ValueError(f"random_displacement(): 'std_mm' must be a number >= 0, got {std_mm!r}")
    if not (is_integer(control_points) and control_points >= 2):
        raise ValueError(
            "random_displacement(): 'control_points' must be an integer >= 2, "
            f"got {control_points!r}"
        )
    c = control_points
    raw = std_mm * torch.randn(c**3, 3, generator=generator, dtype=torch.float64)
    positions = control_point_positions(image, c).reshape(-1, 3)
    field = remove_rigid_part(raw.to(positions.device), positions)
    return field.T.reshape(3, c, c, c).contiguous()


def warp_channels(
    data: Tensor, affine: Tensor, displacement_mm: Tensor, mode: str = "bilinear"
) -> Tensor:
    """Channels on one grid deformed by a displacement field: ``J(x) = I(x + d(x))``.

    Args:
        data: (C, I, J, K) channels (floating point).
        affine: (4, 4) voxel -> world affine of their grid.
        displacement_mm: (3, c, c, c) world-frame displacements in mm on a control grid over the
            voxel grid corner to corner (:func:`random_displacement` of an image on this grid).
        mode: ``"bilinear"`` (trilinear) or ``"nearest"``.

    Returns:
        (C, I, J, K) deformed channels in ``data``'s dtype; 0 where ``x + d(x)`` leaves the grid.
    """
    grid = Image(data[0], affine)
    field = functional.interpolate(
        displacement_mm[None].to(torch.float64),
        size=tuple(data.shape[1:]),
        mode="trilinear",
        align_corners=True,
    )[0]
    points = voxel_centres(grid) + field.movedim(0, -1).to(data.device)
    to_grid = world_to_grid(grid).to(points.device)
    return sample_channels(data, points @ to_grid[:, :3].T + to_grid[:, 3], mode)
