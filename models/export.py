"""The three plain modules behind the ONNX interface (design.md §3), built from a trained agent.

    encoder.onnx  (points (B, N, 3), features (B, N, 4)[, normals (B, N_obj, 3)]) → point_features (B, N_obj, D)
    actor.onnx    (point_features (B, N_obj, D), noise (B, N_obj, S, 3))   → motion (B, N_obj, 3)
    critic.onnx   (point_features (B, N_obj, D), motion (B, N_obj, 3))     → q (B, N_obj, 2)

The forward arguments carry the graph input names of ``robot.onnx_interface`` (``hydo export``
keys its dynamic shapes by them).

The encoder emits features for the object points only: every head is evaluated on object points
(background points reach them through the pooled global feature). The actor is the very ``sample``
used in training, with the K-step chain unrolled and its standard-normal noise an input
(``noise_shape`` below), so a fixed noise gives the same motion in torch and onnxruntime. Deploy
chooses ``argmax_i min(q_i)`` (SAC) or ``argmax_i q1_i`` (TD3), as ``HybridAgent.act(mode="eval")``,
and the graphs hold the same weights it acts with (``HybridAgent.acting_networks("eval")``: by default
the Polyak-averaged encoder and critic).
Plain torch ops only (matmul, relu, tanh, max, layer_norm, softplus): nothing custom to export.
"""

from __future__ import annotations

import copy

import torch
from torch import nn

from models.algos import HybridAgent


class EncoderExport(nn.Module):
    """``(points (B, N, 3) float32 m, features (B, N, 4))`` → ``point_features (B, N_obj, D)``."""

    def __init__(self, agent: HybridAgent) -> None:
        super().__init__()
        self.encoder = copy.deepcopy(agent.acting_networks("eval").encoder).eval()

    def forward(self, points: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        return self.encoder(points, features)


class EncoderWithNormalsExport(EncoderExport):
    """``(points, features, normals (B, N_obj, 3) unit)`` → ``point_features (B, N_obj, D)``: the
    encoder of an agent trained with ``encoder_normals``."""

    def forward(self, points: torch.Tensor, features: torch.Tensor, normals: torch.Tensor) -> torch.Tensor:
        return self.encoder(points, features, normals)


class ActorExport(nn.Module):
    """``(point_features (B, N_obj, D), noise (B, N_obj, S, 3))`` → motion per point ``(B, N_obj, 3)`` in [-1, 1].

    ``deterministic`` follows ``act(mode="eval")``: True for tanh / gauss and for chains exported with
    ``eval_chain_noise="zero"`` (the noise is then unused), False for ddpm / cm whose chain noise is
    the policy.
    """

    def __init__(self, agent: HybridAgent) -> None:
        super().__init__()
        self.motion_policy = copy.deepcopy(agent.acting_networks("eval").motion_policy).eval()
        self.deterministic = not agent.eval_stochastic
        self.n_obj = agent.config.n_obj

    def noise_shape(self, batch: int) -> tuple[int, int, int, int]:
        """Shape of the ``noise`` input for ``batch`` observations."""
        return self.motion_policy.noise_shape(batch, self.n_obj)

    def forward(self, point_features: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
        motion, _ = self.motion_policy.sample(point_features, noise, deterministic=self.deterministic)
        # Deterministic policies ignore their noise; keep it a graph input so every export has the
        # same interface (adds an exact zero).
        return motion + 0.0 * noise[:, :, 0, :]


class CriticExport(nn.Module):
    """``(point_features (B, N_obj, D), motion (B, N_obj, 3))`` → twin Q per point ``(B, N_obj, 2)``."""

    def __init__(self, agent: HybridAgent) -> None:
        super().__init__()
        self.critic = copy.deepcopy(agent.acting_networks("eval").critic).eval()

    def forward(self, point_features: torch.Tensor, motion: torch.Tensor) -> torch.Tensor:
        return self.critic(point_features, motion)


def export_modules(agent: HybridAgent) -> dict[str, nn.Module]:
    """``{"encoder": …, "actor": …, "critic": …}``: frozen copies, ready for ``torch.onnx.export``."""
    encoder = EncoderWithNormalsExport(agent) if agent.config.encoder_normals else EncoderExport(agent)
    mods = {"encoder": encoder, "actor": ActorExport(agent), "critic": CriticExport(agent)}
    for m in mods.values():
        m.requires_grad_(False)
    return mods
