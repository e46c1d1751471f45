"""Small exact utilities shared by the networks and the algorithms (torch only).

Nothing here knows about point clouds or algorithms: Polyak averaging, the tanh change of variables,
an MLP builder, shape checks.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import torch
from torch import nn

LOG_2PI = math.log(2.0 * math.pi)


@torch.no_grad()
def polyak_update(params: Iterable[torch.Tensor], target_params: Iterable[torch.Tensor], tau: float) -> None:
    """In place ``target ← (1 − tau)·target + tau·online`` (SB3's ``polyak_update``).

    One fused ``_foreach_lerp_`` instead of two ops per parameter (per-op overhead matters on the
    2-core CPU). A length mismatch between the two lists raises instead of silently truncating (SB3
    uses ``zip(strict=True)`` for the same reason).
    """
    params, target_params = list(params), list(target_params)
    if len(params) != len(target_params):
        raise ValueError(f"polyak_update: {len(params)} parameters but {len(target_params)} targets")
    torch._foreach_lerp_(target_params, params, tau)


def tanh_log_det(u: torch.Tensor) -> torch.Tensor:
    """``Σ_d log(1 − tanh²(u_d))`` over the last axis: the log-Jacobian of ``a = tanh(u)``.

    ``u (..., 3)`` pre-squash motion → ``(...)``. SB3 and CleanRL write ``log(1 − tanh(u)² + ε)`` with
    ε = 1e-6 because float32 ``tanh(u)`` rounds to exactly ±1 for |u| ≳ 9, and ``log(0) = −inf`` would
    poison the loss; ε caps the term at log(1e-6) ≈ −13.8 per dimension and biases it slightly for
    every u. The identity ``log(1 − tanh²u) = 2·(log 2 − u − softplus(−2u))`` is exact and finite for
    all u, so no ε (and no bias) is needed.
    """
    return (2.0 * (math.log(2.0) - u - nn.functional.softplus(-2.0 * u))).sum(-1)


def mlp(sizes: Sequence[int], activation: type[nn.Module] = nn.ReLU) -> nn.Sequential:
    """``Linear → act`` between consecutive ``sizes``; the last layer is linear only."""
    layers: list[nn.Module] = []
    for i in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[i], sizes[i + 1]))
        if i < len(sizes) - 2:
            layers.append(activation())
    return nn.Sequential(*layers)


def check_shape(
    name: str, t: torch.Tensor, shape: Sequence[int | None], dtype: torch.dtype | None = None
) -> None:
    """Raise ``ValueError`` naming the tensor when ``t`` does not have ``shape`` (None = any size)."""
    if not isinstance(t, torch.Tensor):
        raise TypeError(f"`{name}` must be a torch.Tensor. Got {type(t).__name__}.")
    ok = t.dim() == len(shape) and all(s is None or s == ts for s, ts in zip(shape, t.shape, strict=True))
    if not ok:
        want = "(" + ", ".join("*" if s is None else str(s) for s in shape) + ")"
        raise ValueError(f"`{name}` must have shape {want}. Got {tuple(t.shape)}.")
    if dtype is not None and t.dtype != dtype:
        raise ValueError(f"`{name}` must have dtype {dtype}. Got {t.dtype}.")
