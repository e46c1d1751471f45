"""Critic heads: the scalar and the categorical (HL-Gauss) twin Q."""

import pytest
import torch

from models.heads import TwinQ, hl_gauss_targets


def test_hl_gauss_targets_are_distributions_centred_on_the_target():
    edges = torch.linspace(-4.0, 0.5, 65)
    width = float(edges[1] - edges[0])
    target = torch.tensor([-3.0, -0.52, -0.031, 0.2])
    probs = hl_gauss_targets(target, edges, 0.75 * width)  # (4, 64)
    assert probs.shape == (4, 64) and (probs >= 0).all()
    torch.testing.assert_close(probs.sum(-1), torch.ones(4))
    centres = (edges[1:] + edges[:-1]) / 2
    torch.testing.assert_close(probs @ centres, target, atol=2e-3, rtol=0)  # interior: the mean is the target
    # mass concentrates within ~2σ of the target: a smeared one-hot, not a broad prior
    near = (centres - target[:, None]).abs() < 2 * 0.75 * width
    assert ((probs * near).sum(-1) > 0.9).all()


def test_hl_gauss_targets_clamp_outside_the_range():
    edges = torch.linspace(-1.0, 1.0, 11)
    probs = hl_gauss_targets(torch.tensor([-7.0, 9.0]), edges, 0.15)
    assert probs[0].argmax() == 0 and probs[1].argmax() == 9
    torch.testing.assert_close(probs.sum(-1), torch.ones(2))


def test_categorical_q_is_the_mean_bin_value():
    critic = TwinQ(8, hidden=16, bins=12, value_range=(-2.0, 1.0))
    f, a = torch.randn(3, 5, 8), torch.rand(3, 5, 3) * 2 - 1
    logits = critic.logits(f, a)  # (3, 5, 2, 12)
    assert logits.shape == (3, 5, 2, 12)
    q = critic(f, a)
    torch.testing.assert_close(q, torch.softmax(logits, -1) @ critic.bin_centres)
    torch.testing.assert_close(critic.q1(f, a), q[..., 0])
    assert ((q >= -2.0) & (q <= 1.0)).all()
    # Q stays differentiable in the motion (the actor's gradient)
    a.requires_grad_(True)
    critic(f, a).sum().backward()
    assert a.grad.abs().sum() > 0


def test_bins_are_validated():
    with pytest.raises(ValueError, match="`bins` must be 0"):
        TwinQ(8, bins=1)
    with pytest.raises(ValueError, match="needs its `value_range`"):
        TwinQ(8, bins=4)
    with pytest.raises(ValueError, match="categorical critic"):
        TwinQ(8).logits(torch.zeros(1, 8), torch.zeros(1, 3))


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
