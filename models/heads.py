"""Per-point critic heads and the location policy.

``TwinQ`` scores a motion at a point from that point's features: ``Q(f_i, a_i)``. The location policy
is a softmax of those scores over the object points (background points never get scores: the
encoder only emits object-point features).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from models.motion import MOTION_DIM


class TwinQ(nn.Module):
    """Twin per-point Q heads ``(f (..., D), a (..., 3)) → (..., 2)``.

    Each head is ``Linear(D+3, H) → ReLU → Linear(H, H) → ReLU → Linear(H, 1)``. The two heads are
    stored stacked (leading axis 2) and run as batched matmuls, so both cost one kernel per layer: on
    the 2-core CPU an update is bound as much by per-op overhead as by FLOPs.

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
        motion_dirs: int = 0,
    ) -> None:
        super().__init__()
        if motion_dirs < 0:
            raise ValueError(f"`motion_dirs` must be ≥ 0. Got {motion_dirs}.")
        self.hidden = hidden
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
        self.w2, self.b2 = uniform(2, hidden, hidden, fan_in=hidden), uniform(2, 1, hidden, fan_in=hidden)
        # (2, 1, H) used transposed: a 1-column matmul is ~3× faster on CPU in that layout.
        self.w3, self.b3 = uniform(2, 1, hidden, fan_in=hidden), uniform(2, 1, 1, fan_in=hidden)

    def _hidden(self, x: torch.Tensor, n: int) -> torch.Tensor:
        """``x (R, D+3)`` → last hidden layer ``(n, R, H)`` of the first ``n`` heads."""
        xn = x.expand(n, *x.shape)  # (n, R, D+3)
        h = torch.baddbmm(self.b1[:n], xn, self.w1[:n])  # (n, R, H)
        if self.motion_dirs:
            # The directions come out component-major, (n, R, 3, k) (the stored weights are
            # direction-major, so their columns are permuted per call: 3k·(D+1) numbers), and
            # u_j · a is three fused multiply-adds over contiguous (n, R, k) slices: a product and a
            # sum over a last axis of 3 ran ~8× slower and were ~30 % of a critic pass on 4096 rows.
            k = self.motion_dirs
            wu = self.wu[:n].unflatten(-1, (k, MOTION_DIM)).transpose(-1, -2).flatten(-2)  # (n, D, 3k)
            bu = self.bu[:n].unflatten(-1, (k, MOTION_DIM)).transpose(-1, -2).flatten(-2)  # (n, 1, 3k)
            u = torch.baddbmm(bu, xn[..., : self.feature_dim], wu).unflatten(-1, (MOTION_DIM, k))
            a = xn[..., self.feature_dim :]  # (n, R, 3) the motion
            z = u[:, :, 0] * a[..., 0:1]  # (n, R, k): u_j · a, one motion component at a time
            for d in range(1, MOTION_DIM):
                z = torch.addcmul(z, u[:, :, d], a[..., d : d + 1])
            h = torch.baddbmm(h, z, self.wz[:n])  # (n, R, H)
        return torch.relu(torch.baddbmm(self.b2[:n], torch.relu(h), self.w2[:n]))  # (n, R, H)

    def _heads(self, x: torch.Tensor, n: int) -> torch.Tensor:
        """``x (R, D+3)`` → Q ``(n, R)`` for the first ``n`` heads."""
        h = self._hidden(x, n)
        if h.dtype != torch.float32:
            # Under bf16 autocast (the trainer's precision = "bf16") the output layer stays fp32: a
            # bf16 Q near -0.1 m would be rounded to 0.5 mm steps, the size of the differences
            # between points the location policy ranks and of a late TD error. It is H MACs per row.
            with torch.autocast("cpu", enabled=False):
                q = torch.baddbmm(self.b3[:n], h.float(), self.w3[:n].transpose(1, 2))
            return q.squeeze(-1)  # (n, R)
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


def location_policy(q: torch.Tensor, temperature: torch.Tensor | float) -> tuple[torch.Tensor, torch.Tensor]:
    """``π_loc(i) = softmax(Q_i / β)`` over object points: ``q (B, N_obj)`` → ``(probs, log_probs)``.

    ``temperature`` β: SAC variants use the auto-tuned location temperature α_loc (then π_loc is the
    optimal policy of the entropy-regularised objective over locations); HACMan uses a fixed 0.1.
    """
    log_probs = torch.log_softmax(q / temperature, dim=-1)  # (B, N_obj)
    return log_probs.exp(), log_probs
