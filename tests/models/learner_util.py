"""Helpers shared by the learner tests (unique module name: tests/ folders share sys.path)."""

import torch

#: Small widths that keep every test fast; the defaults are exercised by bench/learner.py.
SMALL = dict(
    n_obj=16,
    n_bg=16,
    feature_dim=32,
    encoder_hidden=32,
    encoder_global=32,
    actor_hidden=32,
    critic_hidden=32,
    actor_points=8,
    # The update's maths does not depend on what the encoder reads; the default normals input is
    # exercised by test_algos.test_act_and_update_with_normals, tests/test_export.py and test_train.
    encoder_normals=False,
)


def random_obs(batch: int, n_obj: int, n_bg: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """Contract-shaped observation: object cloud of ~5 cm, background on the floor, flows of a few cm."""
    g = torch.Generator().manual_seed(seed)
    pts = torch.cat(
        [
            0.03 * torch.randn(batch, n_obj, 3, generator=g) + torch.tensor([0.0, 0.0, 0.05]),
            torch.cat([0.4 * torch.rand(batch, n_bg, 2, generator=g) - 0.2, torch.zeros(batch, n_bg, 1)], -1),
        ],
        dim=1,
    )
    feats = torch.zeros(batch, n_obj + n_bg, 4)
    feats[:, :n_obj, 0] = 1.0
    feats[:, :n_obj, 1:] = 0.05 * torch.randn(batch, n_obj, 3, generator=g)
    return pts, feats
