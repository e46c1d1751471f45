"""Critic heads: the twin Q and its bilinear motion directions."""

import pytest
import torch

from models.heads import TwinQ


def test_motion_directions_are_bilinear_in_the_motion():
    """With ``motion_dirs`` the first layer sees ``u_j(f) · a``: zero motion adds nothing, the term
    is linear in the motion, and its directions are trained by the critic's gradient."""
    torch.manual_seed(0)
    critic = TwinQ(8, hidden=16, motion_dirs=4)
    plain = TwinQ(8, hidden=16)
    plain.load_state_dict({k: v for k, v in critic.state_dict().items() if k not in ("wu", "bu", "wz")})
    f = torch.randn(3, 5, 8)
    zero = torch.zeros(3, 5, 3)
    torch.testing.assert_close(critic(f, zero), plain(f, zero))  # u · 0 = 0
    a = torch.rand(3, 5, 3) * 2 - 1
    x = torch.cat([f, a], -1).reshape(-1, 11)
    h_a = critic._hidden(x, 2)
    assert not torch.allclose(h_a, plain._hidden(x, 2))  # the bilinear term changes the heads
    critic(f, a).sum().backward()
    assert critic.wu.grad.abs().sum() > 0 and critic.wz.grad.abs().sum() > 0
    with pytest.raises(ValueError, match="`motion_dirs` must be ≥ 0"):
        TwinQ(8, motion_dirs=-1)


def test_the_motion_directions_keep_the_stored_weight_layout():
    """``wu`` / ``bu`` are stored direction-major (column ``3j + d`` is component d of direction j),
    as every checkpoint and export holds them; the forward pass permutes them for its fused sum. The
    heads must equal the plain formula on that layout, or old checkpoints would load scrambled."""
    torch.manual_seed(1)
    critic = TwinQ(8, hidden=16, motion_dirs=4)
    f, a = torch.randn(30, 8), torch.rand(30, 3) * 2 - 1
    want = []
    for i in range(2):
        u = (f @ critic.wu[i] + critic.bu[i]).reshape(30, 4, 3)  # direction-major: (R, k, 3)
        z = torch.einsum("rkd,rd->rk", u, a)
        h = torch.relu(torch.cat([f, a], -1) @ critic.w1[i] + critic.b1[i] + z @ critic.wz[i])
        h = torch.relu(h @ critic.w2[i] + critic.b2[i])
        want.append(h @ critic.w3[i, 0] + critic.b3[i, 0, 0])
    torch.testing.assert_close(critic(f, a), torch.stack(want, -1), rtol=1e-5, atol=1e-6)
