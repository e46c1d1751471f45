"""Per-point critic heads and the location policy.

``TwinQ`` scores a motion at a point from that point's features: ``Q(f_i, a_i)``. The location policy
is a softmax of those scores over the object points (background points never get scores: the
encoder only emits object-point features).
"""

from __future__ import annotations

import math

import torch
from torch import nn
from torch.nn import functional as F

from models.motion import MOTION_DIM


class TwinQ(nn.Module):
    """Twin per-point Q heads ``(f (..., D), a (..., 3)) → (..., 2)``.

    Each head is ``Linear(D+3, H) → [LayerNorm] → ReLU → Linear(H, H) → ReLU → Linear(H, 1)``. The two
    heads are stored stacked (leading axis 2) and run as batched matmuls, so both cost one kernel per
    layer: on the 2-core CPU an update is bound as much by per-op overhead as by FLOPs. LayerNorm
    (optional) keeps the heads' inputs at unit scale while the encoder drifts, which stabilises TD
    learning (as in DroQ / REDQ-style critics).

    With ``bins = K > 0`` each head is a classifier over K value bins spanning ``value_range`` (the
    agent passes ``AgentConfig.critic_value_min/max``; HL-Gauss, Farebrother et al. 2024, "Stop
    Regressing"): the last layer emits K logits and ``Q`` is the
    softmax's mean bin value, so callers still read a scalar Q per head; :meth:`logits` feeds the
    cross-entropy loss of :func:`hl_gauss_targets`. A push that reaches the goal ends the episode
    (Q ≈ −0.03) while one that stops just short keeps paying (Q ≈ −0.5): a cliff in action space that
    a squared-error fit blurs and a categorical fit can keep sharp.

    With ``motion_dirs = k > 0`` the first layer also gets k bilinear terms ``z_j = u_j(f) · a``: each
    head maps the point's features to k directions ``u_j(f) = U_j f + c_j`` (3-vectors, no
    nonlinearity) and dots them with the motion. What a push does is mostly such dot products (the
    push along the contact normal, along the direction to the centroid, along the goal flow, its
    torque about the centroid); a ReLU MLP on ``[f, a]`` can only approximate a product of its
    inputs piecewise, with many units.
    """

    def __init__(
        self,
        feature_dim: int,
        hidden: int = 64,
        layer_norm: bool = False,
        bins: int = 0,
        value_range: tuple[float, float] | None = None,
        motion_dirs: int = 0,
    ) -> None:
        super().__init__()
        if motion_dirs < 0:
            raise ValueError(f"`motion_dirs` must be ≥ 0. Got {motion_dirs}.")
        if bins == 1 or bins < 0:
            raise ValueError(f"`bins` must be 0 (scalar Q) or ≥ 2. Got {bins}.")
        if bins and value_range is None:
            raise ValueError("a categorical critic (bins > 0) needs its `value_range` (lo, hi)")
        self.hidden, self.layer_norm, self.bins = hidden, layer_norm, bins
        self.feature_dim, self.motion_dirs = feature_dim, motion_dirs
        d_in = feature_dim + MOTION_DIM

        def uniform(*shape: int, fan_in: int) -> nn.Parameter:  # nn.Linear's default init
            bound = 1.0 / math.sqrt(fan_in)
            return nn.Parameter(torch.empty(*shape).uniform_(-bound, bound))

        self.w1, self.b1 = uniform(2, d_in, hidden, fan_in=d_in), uniform(2, 1, hidden, fan_in=d_in)
        if motion_dirs:
            k3 = motion_dirs * MOTION_DIM
            self.wu, self.bu = (
                uniform(2, feature_dim, k3, fan_in=feature_dim),
                uniform(2, 1, k3, fan_in=feature_dim),
            )
            self.wz = uniform(2, motion_dirs, hidden, fan_in=d_in + motion_dirs)
        self.ln_weight = nn.Parameter(torch.ones(2, 1, hidden))
        self.ln_bias = nn.Parameter(torch.zeros(2, 1, hidden))
        self.w2, self.b2 = uniform(2, hidden, hidden, fan_in=hidden), uniform(2, 1, hidden, fan_in=hidden)
        if bins:
            self.w3, self.b3 = uniform(2, hidden, bins, fan_in=hidden), uniform(2, 1, bins, fan_in=hidden)
            lo, hi = value_range
            self.register_buffer("bin_edges", torch.linspace(lo, hi, bins + 1))  # (K+1,)
            self.register_buffer("bin_centres", (self.bin_edges[1:] + self.bin_edges[:-1]) / 2)  # (K,)
        else:
            # (2, 1, H) used transposed: a 1-column matmul is ~3× faster on CPU in that layout.
            self.w3, self.b3 = uniform(2, 1, hidden, fan_in=hidden), uniform(2, 1, 1, fan_in=hidden)

    def _hidden(self, x: torch.Tensor, n: int) -> torch.Tensor:
        """``x (R, D+3)`` → last hidden layer ``(n, R, H)`` of the first ``n`` heads."""
        xn = x.expand(n, *x.shape)  # (n, R, D+3)
        h = torch.baddbmm(self.b1[:n], xn, self.w1[:n])  # (n, R, H)
        if self.motion_dirs:
            u = torch.baddbmm(self.bu[:n], xn[..., : self.feature_dim], self.wu[:n])  # (n, R, 3k)
            u = u.unflatten(-1, (self.motion_dirs, MOTION_DIM))  # (n, R, k, 3) directions u_j(f)
            a = xn[..., self.feature_dim :]  # (n, R, 3) the motion
            z = (u * a.unsqueeze(-2)).sum(-1)  # (n, R, k): u_j · a
            h = torch.baddbmm(h, z, self.wz[:n])  # (n, R, H)
        if self.layer_norm:
            h = torch.addcmul(self.ln_bias[:n], F.layer_norm(h, (self.hidden,)), self.ln_weight[:n])
        return torch.relu(torch.baddbmm(self.b2[:n], torch.relu(h), self.w2[:n]))  # (n, R, H)

    def _heads(self, x: torch.Tensor, n: int) -> torch.Tensor:
        """``x (R, D+3)`` → Q ``(n, R)`` for the first ``n`` heads."""
        h = self._hidden(x, n)
        if self.bins:
            probs = torch.softmax(torch.baddbmm(self.b3[:n], h, self.w3[:n]), dim=-1)  # (n, R, K)
            return probs @ self.bin_centres  # (n, R)
        return torch.baddbmm(self.b3[:n], h, self.w3[:n].transpose(1, 2)).squeeze(-1)  # (n, R)

    def forward(self, f: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """``f (..., D)``, ``a (..., 3)`` in [-1, 1] → ``(..., 2)`` (Q1, Q2)."""
        x = torch.cat([f, a], dim=-1)
        q = self._heads(x.reshape(-1, x.shape[-1]), 2)  # (2, R)
        return q.t().reshape(*f.shape[:-1], 2)

    def q1(self, f: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """First head only ``(...)``: TD3's actor loss reads Q1 (half the cost of both)."""
        x = torch.cat([f, a], dim=-1)
        return self._heads(x.reshape(-1, x.shape[-1]), 1).reshape(f.shape[:-1])

    def logits(self, f: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Bin logits of both heads ``(..., 2, K)`` (only with ``bins > 0``)."""
        if not self.bins:
            raise ValueError("logits() needs a categorical critic (bins > 0)")
        x = torch.cat([f, a], dim=-1)
        h = self._hidden(x.reshape(-1, x.shape[-1]), 2)  # (2, R, H)
        z = torch.baddbmm(self.b3, h, self.w3)  # (2, R, K)
        return z.transpose(0, 1).reshape(*f.shape[:-1], 2, self.bins)


def hl_gauss_targets(target: torch.Tensor, bin_edges: torch.Tensor, sigma: float) -> torch.Tensor:
    """HL-Gauss class probabilities ``(B, K)`` of scalar targets ``(B,)``: the mass a normal
    N(target, σ²), truncated to the bins' span, puts in each bin (targets outside are clamped in)."""
    lo, hi = bin_edges[0], bin_edges[-1]
    y = target.clamp(lo, hi)[:, None]  # (B, 1)
    cdf = torch.special.erf((bin_edges[None] - y) / (math.sqrt(2.0) * sigma))  # (B, K+1), 2Φ − 1
    mass = cdf[:, 1:] - cdf[:, :-1]  # (B, K)
    return mass / (cdf[:, -1:] - cdf[:, :1])


def location_policy(q: torch.Tensor, temperature: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
    """``π_loc(i) = softmax(Q_i / β)`` over object points: ``q (B, N_obj)`` → ``(probs, log_probs)``.

    ``temperature`` β: SAC variants use the auto-tuned location temperature α_loc (then π_loc is the
    optimal policy of the entropy-regularised objective over locations); HACMan uses a fixed 0.1.
    """
    log_probs = torch.log_softmax(q / temperature, dim=-1)  # (B, N_obj)
    return log_probs.exp(), log_probs
