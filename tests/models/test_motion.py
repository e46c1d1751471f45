"""Motion policies: the sampling interface, the chain entropy estimators, the consistency boundary."""

import math

import pytest
import torch

from models.common import tanh_log_det
from models.motion import (
    ConsistencyPolicy,
    ConsistencySchedule,
    DDPMPolicy,
    GaussPolicy,
    default_target_entropy,
    make_motion_policy,
)

D = 16
CHAINS = [("ddpm", "bound"), ("ddpm", "learned_std"), ("cm", "bound"), ("cm", "learned_std")]


def policy(kind: str, entropy: str = "bound", seed: int = 0):
    torch.manual_seed(seed)
    return make_motion_policy(kind, D, 32, entropy=entropy)


@pytest.mark.parametrize("kind", ["tanh", "gauss", "ddpm", "cm"])
def test_sample_shapes_range_and_fixed_noise(kind):
    pol = policy(kind)
    f = torch.randn(3, 7, D)
    noise = torch.randn(pol.noise_shape(3, 7))
    motion, log_prob = pol.sample(f, noise)
    assert motion.shape == (3, 7, 3) and log_prob.shape == (3, 7)
    assert motion.abs().max() <= 1.0 and torch.isfinite(log_prob).all()
    again, log_prob_again = pol.sample(f, noise.clone())
    # the noise is the only randomness:
    assert torch.equal(motion, again) and torch.equal(log_prob, log_prob_again)
    if kind != "tanh":
        other, _ = pol.sample(f, torch.randn(pol.noise_shape(3, 7)))
        assert not torch.equal(motion, other)


def test_noise_shape_is_checked():
    pol = policy("cm")
    with pytest.raises(ValueError, match="`noise` must have shape"):
        pol.sample(torch.randn(2, 4, D), torch.randn(2, 4, 3))


def test_tanh_log_det_exact_and_finite():
    u = torch.linspace(-4, 4, 101)[:, None].expand(-1, 3)
    ref = torch.log(1 - torch.tanh(u) ** 2).sum(-1)
    assert torch.allclose(tanh_log_det(u), ref, atol=1e-4)
    assert torch.isfinite(tanh_log_det(torch.full((1, 3), 50.0))).all()  # float32 tanh(50) == 1 exactly


def test_gauss_log_prob_matches_torch_distributions():
    pol = policy("gauss")
    f = torch.randn(2, 5, D)
    noise = torch.randn(pol.noise_shape(2, 5))
    motion, log_prob = pol.sample(f, noise)
    mean, log_std = pol.net(f).chunk(2, -1)
    log_std = GaussPolicy.LOG_STD_MIN + 0.5 * (GaussPolicy.LOG_STD_MAX - GaussPolicy.LOG_STD_MIN) * (
        torch.tanh(log_std) + 1
    )
    base = torch.distributions.Normal(mean, log_std.exp())
    dist = torch.distributions.TransformedDistribution(base, [torch.distributions.TanhTransform()])
    u = mean + log_std.exp() * noise[:, :, 0]
    assert torch.allclose(log_prob, base.log_prob(u).sum(-1) - tanh_log_det(u), atol=1e-5)
    assert torch.allclose(log_prob, dist.log_prob(motion.clamp(-1 + 1e-6, 1 - 1e-6)).sum(-1), atol=1e-3)


@pytest.mark.parametrize("kind,entropy", CHAINS)
def test_chain_entropy_gradient_is_nonzero(kind, entropy):
    """The chain's log-prob estimate must depend on θ (a fixed-variance path sum would not)."""
    pol = policy(kind, entropy)
    f = torch.randn(4, 8, D)
    _, log_prob = pol.sample(f, torch.randn(pol.noise_shape(4, 8)))
    log_prob.mean().backward()
    grads = [p.grad for p in pol.denoiser.parameters() if p.grad is not None]
    total = sum(g.abs().sum() for g in grads)
    assert grads and total > 1e-4
    assert pol.denoiser.hidden.weight.grad.abs().sum() > 0  # through the network, not just a bias


@pytest.mark.parametrize("kind", ["ddpm", "cm"])
def test_fixed_variance_path_sum_alone_has_zero_gradient(kind):
    """Why the bound is needed: Σ_k log p_θ on the reparameterised chain is a constant in θ."""
    pol = policy(kind, "bound")
    f = torch.randn(4, 8, D)
    noise = torch.randn(pol.noise_shape(4, 8))
    pol.entropy = "path"  # neither "bound" nor "learned_std": the plain fixed-variance path density
    motion, log_prob = pol.sample(f, noise)
    u = torch.atanh(motion.clamp(-1 + 1e-6, 1 - 1e-6))
    path = log_prob + tanh_log_det(u)  # remove the (θ-dependent) change of variables
    path.sum().backward()
    grad = sum(p.grad.abs().sum() for p in pol.denoiser.parameters() if p.grad is not None)
    assert grad < 1e-3 * (1 + path.abs().sum())


@pytest.mark.parametrize("kind", ["gauss", "ddpm", "cm"])
def test_raising_alpha_widens_motions(kind):
    """Train the motion policy on ``α·log π − Q`` and compare the spread of its samples.

    The critic is a gentle bowl ``Q(a) = −2‖a‖²`` rather than flat: with Adam a flat critic makes the
    loss ``α·log π`` whose updates Adam normalises, so α would only scale the loss, not the result.
    With a bowl the optimum ∝ exp(Q/α) widens with α, which is what the temperature is for.
    """
    spreads = {}
    for alpha in (0.003, 0.3):
        pol = policy(kind, seed=1)
        opt = torch.optim.Adam(pol.parameters(), lr=3e-3)
        f = torch.randn(1, 64, D)
        g = torch.Generator().manual_seed(0)
        for _ in range(150):
            motion, log_prob = pol.sample(f, torch.randn(pol.noise_shape(1, 64), generator=g))
            loss = (alpha * log_prob + 2.0 * motion.pow(2).sum(-1)).mean()
            opt.zero_grad()
            loss.backward()
            opt.step()
        with torch.no_grad():
            motion, _ = pol.sample(f.expand(16, -1, -1), torch.randn(pol.noise_shape(16, 64), generator=g))
        spreads[alpha] = motion.std(dim=0).mean().item()  # spread of samples at the same point
    assert spreads[0.3] > 1.5 * spreads[0.003], spreads


def test_consistency_boundary_condition_is_exact():
    pol = policy("cm")
    eps = pol.schedule.sigma_min
    c_skip, c_out, _ = pol.coefficients(torch.tensor(eps))
    assert c_skip.item() == 1.0 and c_out.item() == 0.0
    f, x = torch.randn(10, D), 3 * torch.randn(10, 3)
    assert torch.equal(pol.consistency_fn(f, x, eps), x)
    assert not torch.allclose(pol.consistency_fn(f, x, 1.0), x)


def test_consistency_sampler_uses_the_consistency_function():
    """The folded sampler equals chaining ``consistency_fn`` by hand with the same noise."""
    pol = policy("cm")
    s: ConsistencySchedule = pol.schedule
    f = torch.randn(1, 5, D)
    noise = torch.randn(pol.noise_shape(1, 5))
    motion, _ = pol.sample(f, noise)
    levels = s.levels().float()
    u = s.sigma_max * noise[0, :, 0]
    for j in range(s.n_steps):
        x0 = pol.consistency_fn(f[0], u, levels[j])
        u = x0 + math.sqrt(levels[j + 1] ** 2 - s.sigma_min**2) * noise[0, :, j + 1]
    assert torch.allclose(motion[0], torch.tanh(u), atol=1e-5)


def test_ddpm_schedule_buffers_and_final_std():
    pol = policy("ddpm")
    assert isinstance(pol, DDPMPolicy)
    assert pol.betas.shape == (5,) and pol.alphas_cumprod[-1] < 0.01  # u^K ~ N(0, I) at K = 5
    assert pol.step_std[-1] == pytest.approx(pol.schedule.final_std)  # last step keeps a density
    assert all(s > 0 for s in pol.step_std)


def test_default_target_entropies():
    assert default_target_entropy("gauss") == -3.0
    assert default_target_entropy("ddpm") < default_target_entropy("cm") < -3.0  # bounds are loose
    assert default_target_entropy("cm", "learned_std") == -15.0
    assert isinstance(policy("cm"), ConsistencyPolicy)
