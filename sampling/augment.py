"""Scanner-realistic augmentation of 2D slices, drawn then applied (TorchIO's sample-then-apply).

:func:`draw_augment_params` draws one :class:`AugmentParams` (a few tensors per slice) from a
``torch.Generator`` and nothing else; :func:`apply_augment` is a deterministic function of the
slices and those parameters, so an augmentation can be recorded and replayed exactly.

Intensity augmentations act on batches of slices ``(B, H, W)``, in this order (the order in which
the effects arise in a scanner):

1. **Gamma** (contrast): ``y = sign(x) m (|x| / m) ** gamma`` with ``m = max |x|`` over the slice,
   i.e. the power law acts on intensities normalised to [0, 1] and the slice's maximum and its zeros
   are kept.
2. **Bias field** (coil sensitivity): the slice is multiplied by ``b = exp(L) / mean(exp(L))``,
   where ``L(p, q) = sum c_ij P_i(p) P_j(q)`` is a 2D polynomial of total degree
   ``1 <= i + j <= order`` in Legendre polynomials ``P_i`` of the pixel coordinates ``p, q``
   normalised to [-1, 1] along array axes 0 and 1. The field is smooth, positive and has mean
   exactly 1 over the slice.
3. **Rician noise** (magnitude images): ``y = sqrt((x + s n1) ** 2 + (s n2) ** 2)`` with ``n1, n2``
   standard normal per pixel and ``s = sigma * ref``, ``ref`` the slice's 99th percentile of ``|x|``
   (nearest rank; the maximum when that percentile is 0, so an all-zero slice gets no noise).
   ``sigma`` is relative.
4. **Intensity scaling** (arbitrary scanner scale): ``y = scale * x``.

Geometric augmentations are not applied to pixels, because they change the slice's true pose:

* **In-plane shifts** move the slice plane within itself. :func:`shift_poses` applies them to the
  poses *before* sampling (``t += R (du, dv, 0)``), so the sampled slice is the shifted one and the
  label (computed from the shifted pose) stays exact; :class:`svr.sampling.dataset.SliceStream` does
  this with its ``shift_mm`` option.
* **Resolution and thickness jitter** is a property of the sampling (in-plane spacing and PSF):
  :class:`svr.sampling.dataset.SliceStream` draws them per batch (``spacing_range_mm``,
  ``thickness_range_mm``) and samples with them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import torch
from torch import Tensor

from svr.geometry import so3_exp
from svr.validation import check_fraction, check_int, check_number, check_range, is_integer

NOISE_REFERENCE_PERCENTILE = 99.0
"""Percentile (nearest rank) of ``|x|`` over a slice that the relative Rician noise level
multiplies."""

_SEED_HIGH = 2**63 - 1


@dataclass(frozen=True)
class SliceAugmentConfig:
    """Probabilities and ranges of the slice intensity augmentations.

    Each augmentation is applied to each slice independently with its probability; a slice it is
    not applied to gets the identity parameter. The defaults follow what the peers use (SVoRT:
    Rician noise with sigma uniform in [0, 0.03] of the 99th percentile, bias field and gamma;
    TorchIO: third-order polynomial bias fields, gamma of about exp(+-0.3)).

    Attributes:
        scale_prob: Probability of intensity scaling.
        scale_range: ``(low, high)`` of the intensity factor, drawn log-uniformly;
            ``0 < low <= high``. Default (0.8, 1.25).
        gamma_prob: Probability of a gamma change.
        gamma_range: ``(low, high)`` of the exponent, drawn log-uniformly; ``0 < low <= high``.
            Default (0.7, 1.4).
        bias_prob: Probability of a bias field.
        bias_order: Highest total degree of the log bias field's Legendre polynomial, >= 1.
        bias_coefficient_max: Each coefficient of the log field is uniform in
            ``[-bias_coefficient_max, +bias_coefficient_max]``, >= 0. Default 0.3.
        noise_prob: Probability of Rician noise.
        noise_sigma_max: The relative noise level ``sigma`` is uniform in ``[0, noise_sigma_max]``
            (a fraction of the slice's 99th intensity percentile), >= 0. Default 0.03.

    Raises:
        ConfigFieldError: On construction, naming the field, if a value is out of its range.
    """

    scale_prob: float = 0.5
    scale_range: tuple[float, float] = (0.8, 1.25)
    gamma_prob: float = 0.5
    gamma_range: tuple[float, float] = (0.7, 1.4)
    bias_prob: float = 0.5
    bias_order: int = 3
    bias_coefficient_max: float = 0.3
    noise_prob: float = 1.0
    noise_sigma_max: float = 0.03

    def __post_init__(self) -> None:
        owner = "SliceAugmentConfig"
        for name in ("scale_prob", "gamma_prob", "bias_prob", "noise_prob"):
            check_fraction(owner, name, getattr(self, name))
        for name in ("scale_range", "gamma_range"):
            check_range(owner, name, getattr(self, name), gt=0)
        check_int(owner, "bias_order", self.bias_order, minimum=1)
        for name in ("bias_coefficient_max", "noise_sigma_max"):
            check_number(owner, name, getattr(self, name), ge=0)


@dataclass(frozen=True)
class AugmentParams:
    """The drawn parameters of one batch of slice augmentations (float64, one entry per slice).

    Attributes:
        scale: (B,) intensity factors (1: none).
        gamma: (B,) gamma exponents (1: none).
        bias_coefficients: (B, n + 1, n + 1) Legendre coefficients ``c_ij`` of the log bias field,
            ``n`` the bias order; zero where ``i + j == 0`` or ``i + j > n`` (all zero: none).
        noise_sigma: (B,) relative Rician noise levels (0: none).
        noise_seed: (B,) int64 seeds of each slice's noise fields, drawn on the slices' device.

    Raises:
        ValueError: On construction, if the shapes do not agree.
    """

    scale: Tensor
    gamma: Tensor
    bias_coefficients: Tensor
    noise_sigma: Tensor
    noise_seed: Tensor

    def __post_init__(self) -> None:
        b = self.batch_size
        for name in ("gamma", "noise_sigma", "noise_seed"):
            if tuple(getattr(self, name).shape) != (b,):
                raise ValueError(
                    f"AugmentParams: '{name}' must have shape ({b},) like 'scale', "
                    f"got {tuple(getattr(self, name).shape)}"
                )
        c = self.bias_coefficients
        if c.dim() != 3 or c.shape[0] != b or c.shape[1] != c.shape[2] or c.shape[1] < 1:
            raise ValueError(
                f"AugmentParams: 'bias_coefficients' must have shape ({b}, n + 1, n + 1), "
                f"got {tuple(c.shape)}"
            )

    @property
    def batch_size(self) -> int:
        """Number ``B`` of slices the parameters are for."""
        return self.scale.shape[0]

    @classmethod
    def identity(
        cls, batch: int, bias_order: int = 3, device: torch.device | str | None = None
    ) -> AugmentParams:
        """Parameters that leave every slice unchanged.

        Args:
            batch: Number of slices ``B``.
            bias_order: Order ``n`` of the (all-zero) bias coefficients.
            device: Device of the tensors; ``None`` for the CPU.

        Returns:
            The identity parameters.
        """
        kw: dict[str, Any] = {"dtype": torch.float64, "device": device}
        return cls(
            scale=torch.ones(batch, **kw),
            gamma=torch.ones(batch, **kw),
            bias_coefficients=torch.zeros(batch, bias_order + 1, bias_order + 1, **kw),
            noise_sigma=torch.zeros(batch, **kw),
            noise_seed=torch.zeros(batch, dtype=torch.int64, device=device),
        )


def draw_augment_params(
    config: SliceAugmentConfig, batch: int, generator: torch.Generator
) -> AugmentParams:
    """Draw the augmentation parameters of a batch of slices from ``generator`` only.

    The same number of values is drawn whatever the probabilities, so changing one probability
    does not change the other parameters drawn from a seed.

    Args:
        config: Probabilities and ranges.
        batch: Number of slices ``B``, >= 0.
        generator: The source of randomness; the parameters are on its device.

    Returns:
        The parameters (see :class:`AugmentParams`).

    Raises:
        ValueError: If ``batch`` is not a non-negative integer.
        TypeError: If ``generator`` is not a ``torch.Generator``.
    """
    if not isinstance(generator, torch.Generator):
        raise TypeError(
            f"draw_augment_params(): 'generator' must be a torch.Generator, "
            f"got {type(generator).__name__}"
        )
    if not (is_integer(batch) and batch >= 0):
        raise ValueError(
            f"draw_augment_params(): 'batch' must be a non-negative integer, got {batch!r}"
        )
    kw: dict[str, Any] = {
        "generator": generator,
        "dtype": torch.float64,
        "device": generator.device,
    }
    n = config.bias_order

    def log_uniform(value_range: tuple[float, float]) -> Tensor:
        low, high = math.log(value_range[0]), math.log(value_range[1])
        return torch.exp(low + (high - low) * torch.rand(batch, **kw))

    applied = torch.rand(batch, 4, **kw) < torch.tensor(
        [config.scale_prob, config.gamma_prob, config.bias_prob, config.noise_prob],
        dtype=torch.float64,
        device=generator.device,
    )
    scale = log_uniform(config.scale_range)
    gamma = log_uniform(config.gamma_range)
    degree = torch.arange(n + 1, device=generator.device)
    terms = degree[:, None] + degree[None, :]
    term_mask = (terms >= 1) & (terms <= n)
    coefficients = (2.0 * torch.rand(batch, n + 1, n + 1, **kw) - 1.0) * config.bias_coefficient_max
    sigma = torch.rand(batch, **kw) * config.noise_sigma_max
    seed = torch.randint(
        0, _SEED_HIGH, (batch,), generator=generator, dtype=torch.int64, device=generator.device
    )
    return AugmentParams(
        scale=torch.where(applied[:, 0], scale, torch.ones_like(scale)),
        gamma=torch.where(applied[:, 1], gamma, torch.ones_like(gamma)),
        bias_coefficients=coefficients * (term_mask & applied[:, 2, None, None]),
        noise_sigma=torch.where(applied[:, 3], sigma, torch.zeros_like(sigma)),
        noise_seed=seed,
    )


def _legendre(n: int, x: Tensor) -> Tensor:
    """(n + 1, len(x)) values of the Legendre polynomials ``P_0 .. P_n`` at ``x``."""
    values = [torch.ones_like(x), x]
    for k in range(1, n):
        values.append(((2 * k + 1) * x * values[k] - k * values[k - 1]) / (k + 1))
    return torch.stack(values[: n + 1])


def bias_field(
    coefficients: Tensor, size: tuple[int, int], dtype: torch.dtype = torch.float32
) -> Tensor:
    """Multiplicative bias fields ``exp(L) / mean(exp(L))`` of Legendre coefficients.

    Args:
        coefficients: (B, n + 1, n + 1) coefficients ``c_ij`` of ``L(p, q) = sum c_ij P_i(p)
            P_j(q)``, with ``p`` and ``q`` the pixel coordinates along array axes 0 and 1 mapped
            linearly to [-1, 1] (first pixel -1, last pixel +1).
        size: (H, W) pixels.
        dtype: dtype of the result (computed in float64).

    Returns:
        (B, H, W) positive fields with mean 1 over each slice, on ``coefficients``' device.
    """
    c = coefficients.to(torch.float64)
    n = c.shape[-1] - 1
    kw: dict[str, Any] = {"dtype": torch.float64, "device": c.device}
    p = _legendre(n, torch.linspace(-1.0, 1.0, size[0], **kw))
    q = _legendre(n, torch.linspace(-1.0, 1.0, size[1], **kw))
    field = torch.exp(torch.einsum("bij,ih,jw->bhw", c, p, q))
    return (field / field.mean(dim=(1, 2), keepdim=True)).to(dtype)


def _check_slices(slices: Tensor, params: AugmentParams) -> None:
    if not (isinstance(slices, Tensor) and slices.is_floating_point() and slices.dim() == 3):
        raise ValueError(
            "apply_augment(): 'slices' must be a floating-point tensor (B, H, W), got "
            f"{tuple(slices.shape) if isinstance(slices, Tensor) else type(slices).__name__}"
        )
    if slices.shape[0] != params.batch_size:
        raise ValueError(
            f"apply_augment(): 'params' are for {params.batch_size} slices, "
            f"'slices' has {slices.shape[0]}"
        )


def apply_augment(slices: Tensor, params: AugmentParams) -> Tensor:
    """Apply drawn augmentations: gamma, bias field, Rician noise, then scaling (module docstring).

    Deterministic given ``params`` (and the device: noise fields are drawn on the slices' device
    from each slice's ``noise_seed``). Slices whose parameters are the identity are returned
    unchanged, bit for bit.

    Args:
        slices: (B, H, W) floating-point slices (non-negative magnitudes for Rician noise to be
            meaningful).
        params: Parameters for ``B`` slices, from :func:`draw_augment_params`.

    Returns:
        (B, H, W) augmented slices, a new tensor in the dtype and device of ``slices``.

    Raises:
        ValueError: If ``slices`` is not (B, H, W) floating point or ``params`` is for another
            batch size.
    """
    _check_slices(slices, params)
    x = slices.clone()
    size = cast("tuple[int, int]", tuple(x.shape[1:]))

    rows = _rows(params.gamma != 1, x.device)
    if len(rows):
        y = x[rows]
        peak = y.flatten(1).abs().amax(dim=1)[:, None, None]
        peak = torch.where(peak > 0, peak, torch.ones_like(peak))  # all-zero slices stay zero
        gamma = params.gamma[rows.to(params.gamma.device)].to(x)[:, None, None]
        x[rows] = torch.sign(y) * peak * (y.abs() / peak) ** gamma

    rows = _rows(params.bias_coefficients.flatten(1).ne(0).any(dim=1), x.device)
    if len(rows):
        coefficients = params.bias_coefficients[rows.to(params.bias_coefficients.device)]
        x[rows] = x[rows] * bias_field(coefficients.to(x.device), size, x.dtype)

    rows = _rows(params.noise_sigma > 0, x.device)
    if len(rows):
        y = x[rows]
        magnitude = y.flatten(1).abs()
        rank = max(1, math.ceil(NOISE_REFERENCE_PERCENTILE / 100.0 * magnitude.shape[1]))
        ref = torch.kthvalue(magnitude, rank, dim=1).values
        ref = torch.where(ref > 0, ref, magnitude.amax(dim=1))
        sigma = params.noise_sigma[rows.to(params.noise_sigma.device)].to(x)
        std = (sigma * ref)[:, None, None]
        seeds = params.noise_seed[rows.to(params.noise_seed.device)].tolist()
        noise = torch.stack(
            [
                torch.randn(
                    (2, *size),
                    generator=torch.Generator(device=x.device).manual_seed(seed),
                    dtype=x.dtype,
                    device=x.device,
                )
                for seed in seeds
            ]
        )
        x[rows] = torch.sqrt((y + std * noise[:, 0]) ** 2 + (std * noise[:, 1]) ** 2)

    rows = _rows(params.scale != 1, x.device)
    if len(rows):
        x[rows] = x[rows] * params.scale[rows.to(params.scale.device)].to(x)[:, None, None]
    return x


def _rows(selected: Tensor, device: torch.device) -> Tensor:
    """Indices (on ``device``) of the slices a (B,) boolean ``selected`` picks."""
    return torch.nonzero(selected).flatten().to(device)


def shift_poses(poses: Tensor, shifts_mm: Tensor) -> Tensor:
    """Move slices within their own plane: ``t += R (du, dv, 0)``.

    The slice sampled at the shifted pose is the original slice translated by ``(-du, -dv)`` mm
    in the plane: its pixel ``(a, b)`` sees what the original's pixel ``(a + du / s, b + dv / s)``
    sees (``s`` the in-plane spacing). Apply this before sampling and compute labels from the
    shifted poses, so that the labels stay exact.

    Args:
        poses: (..., 6) pose vectors (rad, mm) mapping the slice plane to the target frame.
        shifts_mm: (..., 2) shifts ``(du, dv)`` in mm along the slice's array axes 0 and 1,
            broadcastable with ``poses[..., :2]``.

    Returns:
        (..., 6) shifted poses (same rotation) in the dtype of ``poses``, batch dimensions
        broadcast.

    Raises:
        ValueError: If the last dimensions are not 6 and 2.
    """
    if poses.shape[-1:] != (6,) or shifts_mm.shape[-1:] != (2,):
        raise ValueError(
            "shift_poses(): 'poses' must be (..., 6) and 'shifts_mm' (..., 2), got "
            f"{tuple(poses.shape)} and {tuple(shifts_mm.shape)}"
        )
    R = so3_exp(poses[..., :3])
    offset = (R[..., :, :2] * shifts_mm.to(R.dtype).unsqueeze(-2)).sum(-1)
    return torch.cat([poses[..., :3].expand_as(offset), poses[..., 3:] + offset], dim=-1)
