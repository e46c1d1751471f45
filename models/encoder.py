"""Per-point point-cloud encoder: a small PointNet.

Why not HACMan's PointNet++: on the 2-core CPU this project trains on, a HACMan-size PointNet++
costs 0.3–3 s per gradient update (``../shared/reference/measurements.md``); the kNN-gathered tensors
of its set-abstraction layers dominate. A PointNet (shared per-point MLP, max-pooled global context
concatenated back per point) is a handful of dense matmuls, exports to ONNX with plain ops and leaves
room for the K-step motion chain, which has to run on every object point in every update.

Architecture (H = ``hidden``, G = ``global_dim``, D = ``out_dim``)::

    x_i   = [ (p_i − mean(p_obj)) / s,  is_object_i,  goal_flow_i / s (, n_i) ]  (7,) or (10,)
                                                     s = length_scale; n_i: normal (0 on background)
    h_i   = MLP_local(x_i)                                                  (H,)    all N points
    g     = [ max_{i ∈ obj} W_g h_i , max_{i ∈ bg} W_g h_i ]                (2G,)   per cloud
    f_i   = LayerNorm(MLP_head(relu(W_h h_i + W_c g)))                      (D,)    object points

With ``normals=True`` the object points' outward unit normals (the observation's ``normals``, which
the primitive approaches along) enter each point's input. What a push at a point does depends on the
surface there, and a PointNet cannot estimate a normal from one point. With them the 60-minute planar
runs reached 78–82 % instead of 62–68 % (docs/results.md), so ``AgentConfig.encoder_normals`` is on
by default.

Local shape beyond the normal was tried twice and not kept: a learned kNN EdgeConv (2.3× the time
per step) and each point's neighbourhood mean normal as an input (one 6D run: 52.8 % on unseen
objects, below every default seed): docs/experiments.md.

Only object points get output features: every head (location, motion, critic) is evaluated on
object points only, so background points contribute through the global feature alone and the head
layers run on N_obj instead of N rows.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn

from models.common import check_shape

FEATURE_DIM = 4  # [is_object, goal_flow_xyz]: the observation contract's per-point features


def _max_pool(x: torch.Tensor) -> torch.Tensor:
    """``x (B, N, G)`` → ``(B, G)``, the max over the points. Without grad (target encoder, acting)
    ``amax``, ~13× faster on this CPU than ``max(dim)``, which also finds the indices; with grad
    ``max(dim)``, whose backward is cheaper than ``amax``'s. The same values either way."""
    return x.max(dim=1).values if x.requires_grad else x.amax(dim=1)


class EncoderContext(NamedTuple):
    """Intermediate per-point and per-cloud tensors; ``head`` turns them into features."""

    local: torch.Tensor  # (B, N_obj, H) per-point local features of the object points
    context: torch.Tensor  # (B, H) the global feature's contribution to the head's first layer


class PointEncoder(nn.Module):
    """Point cloud → per-object-point features.

    Args:
        n_obj: object points per cloud (they come first in ``points``).
        n_bg: background points per cloud (after the object points).
        out_dim: D, the per-point feature size fed to the heads.
        hidden: H, width of the per-point MLPs.
        global_dim: G, width of each max-pooled global feature (object and background).
        length_scale: metres mapped to one network unit for positions and goal flow (objects are
            ~5–20 cm, the bin ~0.5 m, so 0.1 m keeps inputs at unit scale).
        normals: take the object points' normals ``(B, N_obj, 3)`` as a third input.
    """

    def __init__(
        self,
        n_obj: int,
        n_bg: int,
        out_dim: int = 64,
        hidden: int = 64,
        global_dim: int = 64,
        length_scale: float = 0.1,
        normals: bool = False,
    ) -> None:
        super().__init__()
        if n_obj < 1 or n_bg < 0:
            raise ValueError(f"`n_obj` must be ≥ 1 and `n_bg` ≥ 0. Got {n_obj}, {n_bg}.")
        self.n_obj, self.n_bg, self.out_dim = n_obj, n_bg, out_dim
        self.uses_normals = normals
        self.register_buffer("inv_scale", torch.tensor(1.0 / length_scale))
        n_in = 10 if normals else 7
        self.local = nn.Sequential(nn.Linear(n_in, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU())
        self.global_proj = nn.Linear(hidden, global_dim)
        n_pools = 2 if n_bg > 0 else 1
        self.head_local = nn.Linear(hidden, hidden)
        self.head_global = nn.Linear(n_pools * global_dim, hidden, bias=False)
        self.head_out = nn.Sequential(nn.ReLU(), nn.Linear(hidden, out_dim), nn.LayerNorm(out_dim))

    def normalise(
        self, points: torch.Tensor, features: torch.Tensor, normals: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``points (B, N, 3)`` metres, ``features (B, N, 4)`` (, ``normals (B, N_obj, 3)``) → network
        input ``(B, N, C)``: C = 7, or 10 with normals.

        Positions are taken relative to the object's centroid (translation invariance: the same push
        on the same object means the same thing anywhere in the bin) and, like the goal flow, divided
        by ``length_scale`` so exported graphs take raw metres.
        """
        centre = points[:, : self.n_obj].mean(dim=1, keepdim=True)  # (B, 1, 3)
        pos = (points - centre) * self.inv_scale  # (B, N, 3)
        flow = features[..., 1:] * self.inv_scale  # (B, N, 3)
        parts = [pos, features[..., :1], flow]
        if self.uses_normals:  # background points have no normal: zeros (their is_object flag is 0)
            parts.append(torch.cat([normals, torch.zeros_like(points[:, self.n_obj :])], dim=1))
        return torch.cat(parts, dim=-1)  # (B, N, C)

    def encode_context(
        self, points: torch.Tensor, features: torch.Tensor, normals: torch.Tensor | None = None
    ) -> EncoderContext:
        """Everything up to the per-point head: ``(B, N, 3), (B, N, 4)`` (, ``(B, N_obj, 3)``) →
        :class:`EncoderContext`."""
        n = self.n_obj + self.n_bg
        check_shape("points", points, (None, n, 3))
        check_shape("features", features, (None, n, FEATURE_DIM))
        if self.uses_normals:
            if normals is None:
                raise ValueError(
                    "this encoder takes the object points' normals: pass `normals` (B, N_obj, 3)"
                )
            check_shape("normals", normals, (points.shape[0], self.n_obj, 3))
        x = self.normalise(points, features, normals)
        h = self.local(x)  # (B, N, H)
        h_obj = h[:, : self.n_obj]  # (B, N_obj, H)
        g_all = self.global_proj(h)  # (B, N, G)
        pools = [_max_pool(g_all[:, : self.n_obj])]  # (B, G)
        if self.n_bg > 0:
            pools.append(_max_pool(g_all[:, self.n_obj :]))  # (B, G)
        g = torch.relu(torch.cat(pools, dim=-1))  # (B, 2G)
        return EncoderContext(local=h_obj, context=self.head_global(g))

    def encode_for_update(
        self,
        points: torch.Tensor,
        features: torch.Tensor,
        normals: torch.Tensor | None,
        index: torch.Tensor,
    ) -> tuple[torch.Tensor, EncoderContext]:
        """The critic loss's encoding: features of the executed points with grad, ``(B, D)``, and the
        detached :class:`EncoderContext` of every point (for the actor), from one pass.

        Exact, and cheaper than differentiating :meth:`encode_context`: the loss reaches the per-point
        MLP only through the executed point's local row and the max-pools, and a max-pool's gradient
        goes to its argmax row alone. So at most ``1 + n_pools·G`` of the N rows per cloud receive any
        gradient. All N rows are encoded without grad (no activations kept) to find each pool's argmax;
        then only the executed point and the argmax rows are encoded again with grad, and the pools are
        taken over them: the same values (the argmax of every channel is among them) and the same
        gradient (a row that is not an argmax gets none). Backward then runs on ``1 + n_pools·G``
        rows per cloud instead of N (129 instead of 256 at the defaults). ``index (B,)`` int64 into
        the object points.
        """
        n = self.n_obj + self.n_bg
        check_shape("points", points, (None, n, 3))
        check_shape("features", features, (None, n, FEATURE_DIM))
        x = self.normalise(points, features, normals)  # (B, N, C): no parameters, no grad needed
        with torch.no_grad():
            h = self.local(x)  # (B, N, H)
            g_all = self.global_proj(h)  # (B, N, G)
            # max(dim).indices, not argmax: the same kind of row, 1.6-4x faster on a (B, N, G) tensor
            # reduced over N on this CPU (argmax's bf16 path is the slow one)
            picks = [index[:, None], g_all[:, : self.n_obj].max(dim=1).indices]  # (B, 1), (B, G)
            if self.n_bg > 0:
                picks.append(g_all[:, self.n_obj :].max(dim=1).indices + self.n_obj)  # (B, G)
            rows = torch.cat(picks, dim=1)  # (B, S): executed point, object argmaxes, background argmaxes
        g = self.global_proj.out_features
        x_sel = x.gather(1, rows[..., None].expand(-1, -1, x.shape[-1]))  # (B, S, C)
        h_sel = self.local(x_sel)  # (B, S, H), with grad
        g_sel = self.global_proj(h_sel)  # (B, S, G)
        pools = [g_sel[:, : 1 + g].max(dim=1).values]  # (B, G): the executed point is an object point
        if self.n_bg > 0:
            pools.append(g_sel[:, 1 + g :].max(dim=1).values)  # (B, G)
        context = self.head_global(torch.relu(torch.cat(pools, dim=-1)))  # (B, H)
        f_taken = self.head(h_sel[:, 0], context)  # (B, D)
        return f_taken, EncoderContext(local=h[:, : self.n_obj], context=context.detach())

    def head(self, local: torch.Tensor, context: torch.Tensor) -> torch.Tensor:
        """Per-point features from local rows ``(..., H)`` and their cloud's context ``(..., H)``."""
        return self.head_out(self.head_local(local) + context)  # (..., D)

    def forward(
        self, points: torch.Tensor, features: torch.Tensor, normals: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``points (B, N, 3)`` float32 metres (object points first), ``features (B, N, 4)``
        ``[is_object, goal_flow_xyz]`` (, ``normals (B, N_obj, 3)`` unit, when the encoder takes them;
        ignored otherwise) → object-point features ``(B, N_obj, D)``."""
        ctx = self.encode_context(points, features, normals)
        return self.head(ctx.local, ctx.context[:, None, :])
