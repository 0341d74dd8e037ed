"""Argument checks shared by the geometry, loss and metric functions."""

from __future__ import annotations

import torch
from torch import Tensor


def check_tensor(x: object, func: str, name: str, last_dims: tuple[int, ...]) -> Tensor:
    """Check that ``x`` is a floating-point tensor whose trailing dimensions are ``last_dims``.

    Args:
        x: The argument to check.
        func: Name of the public function, used in the error message.
        name: Name of the argument, used in the error message.
        last_dims: Required sizes of the trailing dimensions; leading dimensions are free.

    Returns:
        ``x`` unchanged.

    Raises:
        TypeError: If ``x`` is not a floating-point tensor.
        ValueError: If the trailing dimensions differ from ``last_dims``.
    """
    expected = "(..., " + ", ".join(str(d) for d in last_dims) + ")"
    if not isinstance(x, Tensor):
        raise TypeError(
            f"{func}(): '{name}' must be a torch.Tensor of shape {expected}, got {type(x).__name__}"
        )
    if not x.is_floating_point():
        raise TypeError(f"{func}(): '{name}' must be a floating-point tensor, got {x.dtype}")
    n = len(last_dims)
    if x.dim() < n or tuple(x.shape[-n:]) != last_dims:
        raise ValueError(f"{func}(): '{name}' must have shape {expected}, got {tuple(x.shape)}")
    return x


def check_se3_matrix(x: object, func: str, name: str) -> Tensor:
    """Check that ``x`` is a floating-point (..., 4, 4) or (..., 3, 4) rigid-transform tensor.

    Raises:
        TypeError: If ``x`` is not a floating-point tensor.
        ValueError: If the trailing dimensions are neither (4, 4) nor (3, 4).
    """
    if isinstance(x, Tensor) and x.dim() >= 2 and tuple(x.shape[-2:]) == (3, 4):
        return check_tensor(x, func, name, (3, 4))
    if isinstance(x, Tensor) and x.dim() >= 2 and tuple(x.shape[-2:]) != (4, 4):
        raise ValueError(
            f"{func}(): '{name}' must have shape (..., 4, 4) or (..., 3, 4), got {tuple(x.shape)}"
        )
    return check_tensor(x, func, name, (4, 4))


def promote_float64(*xs: Tensor) -> tuple[Tensor, ...]:
    """Cast tensors to float64 (for computations that cancel catastrophically in float32)."""
    return tuple(x.to(torch.float64) for x in xs)
