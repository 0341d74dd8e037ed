"""Inner products Z on the SE(3) tangent space at the identity: the default and data-adaptive."""

from __future__ import annotations

import torch
from torch import Tensor

from svr.geometry._validation import check_tensor

DEFAULT_LENGTH_SCALE_MM = 30.0
"""Length L (mm) that makes 1 rad of rotation weigh as much as L mm of translation.

A small rotation ``theta`` about the centre of a brain of radius ``rho`` moves its points by
``sqrt(0.4) rho theta`` in RMS (points uniform in a ball); for a fetal brain with ``rho ~ 45 mm``
that is ~28 mm per radian, rounded to 30 mm.
"""


def default_metric_weights(
    length_scale_mm: float = DEFAULT_LENGTH_SCALE_MM,
    *,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """The default diagonal of Z: ``(1, 1, 1, 1/L^2, 1/L^2, 1/L^2)``.

    With it, ``e^T Z e = theta^2 + |dt|^2 / L^2``: rotation in rad, translation in units of L.

    Args:
        length_scale_mm: L in mm, > 0.
        dtype: Floating dtype of the result (default: torch's default dtype).
        device: Device of the result.

    Returns:
        (6,) weights.
    """
    if not length_scale_mm > 0:
        raise ValueError(
            f"default_metric_weights(): 'length_scale_mm' must be > 0, got {length_scale_mm}"
        )
    s = 1.0 / float(length_scale_mm) ** 2
    return torch.tensor([1.0, 1.0, 1.0, s, s, s], dtype=dtype, device=device)


def validate_metric_weights(weights: Tensor, func: str = "validate_metric_weights") -> Tensor:
    """Check an inner product Z given as a (6,) positive diagonal or a (6, 6) SPD matrix.

    Args:
        weights: (6,) or (6, 6) tensor.
        func: Name of the calling function, for the error message.

    Returns:
        ``weights`` unchanged.

    Raises:
        TypeError: If ``weights`` is not a floating-point tensor.
        ValueError: If its shape is wrong, it has non-finite values, a diagonal entry is not
            positive, or the matrix is not symmetric positive definite.
    """
    if not isinstance(weights, Tensor) or not weights.is_floating_point():
        raise TypeError(
            f"{func}(): 'weights' must be a floating-point torch.Tensor of shape (6,) "
            f"or (6, 6), got {getattr(weights, 'dtype', type(weights).__name__)}"
        )
    if tuple(weights.shape) not in ((6,), (6, 6)):
        raise ValueError(
            f"{func}(): 'weights' must have shape (6,) (a diagonal) or (6, 6) "
            f"(a symmetric positive definite matrix), got {tuple(weights.shape)}"
        )
    w = weights.detach()
    if not bool(torch.isfinite(w).all()):
        raise ValueError(f"{func}(): 'weights' must be finite")
    if w.dim() == 1:
        if not bool((w > 0).all()):
            raise ValueError(
                f"{func}(): 'weights' diagonal entries must all be > 0, got {w.tolist()}"
            )
        return weights
    w64 = w.to(torch.float64)
    if not torch.allclose(w64, w64.T, rtol=1e-5, atol=1e-8 * float(w64.abs().max())):
        raise ValueError(f"{func}(): 'weights' (6, 6) must be symmetric")
    if int(torch.linalg.cholesky_ex(w64).info) != 0:
        raise ValueError(f"{func}(): 'weights' (6, 6) must be positive definite")
    return weights


def estimate_metric_weights(errors: Tensor, normalize: bool = False) -> Tensor:
    """Data-adaptive weights ``diag(cov(errors)^-1)`` (Hou et al., Exp. 1).

    Pass the errors of a model trained with the default weights on a validation set, as given by
    :func:`svr.geometry.se3_error` (``(N, 6)``: rad, mm). Components with large spread get small
    weights. The covariance is the unbiased sample covariance (mean removed), computed in float64.

    Args:
        errors: (N, 6) error vectors at the identity, N >= 7.
        normalize: Scale the result to unit L2 norm, as the authors did.

    Returns:
        (6,) weights, positive, in the dtype and on the device of ``errors``.

    Raises:
        ValueError: If there are too few or non-finite errors, or the covariance is singular
            (e.g. a component that never varies), naming the degenerate components.
    """
    check_tensor(errors, "estimate_metric_weights", "errors", (6,))
    if errors.dim() != 2 or errors.shape[0] < 7:
        raise ValueError(
            "estimate_metric_weights(): 'errors' must have shape (N, 6) with N >= 7 "
            f"(more samples than dimensions), got {tuple(errors.shape)}"
        )
    x = errors.detach().to(torch.float64)
    if not bool(torch.isfinite(x).all()):
        raise ValueError("estimate_metric_weights(): 'errors' contains NaN or Inf")
    cov = torch.cov(x.T)
    scale = cov.diagonal().clamp_min(torch.finfo(torch.float64).tiny).sqrt()
    corr = cov / (scale[:, None] * scale[None, :])
    eigvals, eigvecs = torch.linalg.eigh(corr)
    if float(eigvals[0]) < 1e-10 or float(cov.diagonal().min()) <= 0:
        names = ("r_x", "r_y", "r_z", "t_x", "t_y", "t_z")
        null = eigvecs[:, 0].abs()
        involved = [names[i] for i in range(6) if float(null[i]) > 0.1]
        raise ValueError(
            "estimate_metric_weights(): the covariance of 'errors' is singular "
            f"(degenerate components: {', '.join(involved)}); use more varied data"
        )
    weights = torch.linalg.inv(cov).diagonal()
    if normalize:
        weights = weights / weights.norm()
    return weights.to(dtype=errors.dtype, device=errors.device)
