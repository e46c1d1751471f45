"""The hybrid agent: configuration, acting, the update's maths, checkpoint → resume, export modules."""

import dataclasses
import math

import pytest
import torch
from learner_util import SMALL, random_obs

from models.algos import (
    ALGOS,
    AgentConfig,
    HybridAgent,
    actor_surrogate_weights,
    frozen,
)
from models.checkpoint import load_checkpoint, save_checkpoint
from models.export import export_modules
from models.heads import location_policy
from models.replay import ReplayBatch


def make_batch(b: int, n_obj: int, n_bg: int, seed: int = 0, **override) -> ReplayBatch:
    g = torch.Generator().manual_seed(seed)
    points, features = random_obs(b, n_obj, n_bg, seed)
    next_points, next_features = random_obs(b, n_obj, n_bg, seed + 1)
    fields = dict(
        points=points,
        features=features,
        index=torch.randint(0, n_obj, (b,), generator=g),
        motion=2 * torch.rand(b, 3, generator=g) - 1,
        reward=-0.1 * torch.rand(b, generator=g),
        next_points=next_points,
        next_features=next_features,
        terminated=(torch.rand(b, generator=g) < 0.3).float(),
        truncated=torch.zeros(b),
    )
    fields.update(override)
    return ReplayBatch(**fields)


def test_config_validation_messages():
    with pytest.raises(ValueError, match=r"`algo` must be one of \['hacman', .*\]\. Got nope\."):
        AgentConfig(algo="nope")
    with pytest.raises(
        ValueError, match=r"`chain_entropy` must be one of \['bound', 'learned_std'\]\. Got x\."
    ):
        AgentConfig(chain_entropy="x")
    with pytest.raises(dataclasses.FrozenInstanceError):
        AgentConfig().algo = "hacman"


def test_config_records_resolved_choices():
    d = AgentConfig(algo="hydo-cm").to_dict()
    assert d["chain_entropy"] == "bound"
    assert d["resolved"]["objective"] == "sac" and d["resolved"]["motion"] == "cm"
    assert d["resolved"]["target_entropy_motion"] < -3
    assert AgentConfig.from_dict(d) == AgentConfig(algo="hydo-cm")


def test_algorithm_table():
    assert {a: (s.objective, s.motion) for a, s in ALGOS.items()} == {
        "hacman": ("td3", "tanh"),
        "hacman-diff": ("td3", "ddpm"),
        "hacman-cm": ("td3", "cm"),
        "hydo-gauss": ("sac", "gauss"),
        "hydo": ("sac", "ddpm"),
        "hydo-cm": ("sac", "cm"),
    }


@pytest.mark.parametrize("algo", list(ALGOS))
def test_act_modes(algo):
    agent = HybridAgent(AgentConfig(algo=algo, **SMALL))
    points, features = random_obs(5, 16, 16)
    for mode in ("explore", "eval"):
        index, motion, info = agent.act(points, features, mode, torch.Generator().manual_seed(0))
        assert index.shape == (5,) and index.dtype == torch.int64
        assert ((index >= 0) & (index < 16)).all()  # object points only, never background
        assert motion.shape == (5, 3) and motion.abs().max() <= 1
        assert info["q"].shape == (5, 16) and info["location_probs"].shape == (5, 16)
        again = agent.act(points, features, mode, torch.Generator().manual_seed(0))
        assert torch.equal(index, again[0]) and torch.equal(motion, again[1])  # seeded → reproducible
    _, m1, _ = agent.act(points, features, "eval", torch.Generator().manual_seed(1))
    _, m2, _ = agent.act(points, features, "eval", torch.Generator().manual_seed(2))
    deterministic_eval = not agent.motion_policy.stochastic_eval  # eval is stochastic only for chains
    assert torch.equal(m1, m2) == deterministic_eval
    with pytest.raises(ValueError, match="`mode` must be one of"):
        agent.act(points, features, "greedy")
    with pytest.raises(ValueError, match="`points` must have shape"):
        agent.act(points[:, :20], features[:, :20])


@pytest.mark.parametrize("algo", ["hydo", "hacman-cm"])
def test_actor_subset_estimator_is_unbiased(algo):
    """E_{i∼π_loc}[∇(c_i Q_i + α_m log π_m,i)] equals ∇ Σ_i π_loc(i) J_i (exact, with the softmax)."""
    agent = HybridAgent(AgentConfig(algo=algo, **SMALL))
    sac = agent.is_sac
    f = torch.randn(3, 16, 32)
    noise = torch.randn(agent.motion_policy.noise_shape(3, 16))
    alpha_loc, alpha_m = (0.2, 0.05) if sac else (agent.config.location_beta, 0.0)
    params = list(agent.motion_policy.parameters())

    def grads(loss):
        return torch.autograd.grad(loss, params, allow_unused=True)

    with frozen(agent.critic):
        a, logp = agent.motion_policy.sample(f, noise)
        q = agent._actor_q(f, a)
        pi, log_pi = location_policy(q, alpha_loc)
        j = -q + alpha_loc * log_pi + alpha_m * logp if sac else -q
        exact = grads((pi * j).sum(-1).mean())
        w = actor_surrogate_weights(q.detach(), logp.detach(), alpha_loc, alpha_m, sac)
        a, logp = agent.motion_policy.sample(f, noise)
        q = agent._actor_q(f, a)
        expected = grads((pi.detach() * (w.coef * q + alpha_m * logp)).sum(-1).mean())
    for g1, g2 in zip(exact, expected, strict=True):
        if g1 is None:
            assert g2 is None or g2.abs().max() == 0
        else:
            assert torch.allclose(g1, g2, atol=1e-6, rtol=1e-4)
    assert torch.allclose(w.loss, (pi * j).sum(-1).detach(), atol=1e-6)


@pytest.mark.parametrize("algo", ["hydo-cm", "hacman"])
def test_only_terminated_masks_the_bootstrap(algo):
    """A truncated transition (primitive cap) bootstraps; a terminated one does not."""
    base = HybridAgent(AgentConfig(algo=algo, **SMALL))
    state = base.state_dict()
    targets = {}
    for name, term, trunc in (("terminated", 1.0, 0.0), ("truncated", 0.0, 1.0)):
        agent = HybridAgent(AgentConfig(algo=algo, **SMALL))
        agent.load_state_dict(state)
        batch = make_batch(
            4,
            16,
            16,
            reward=torch.zeros(4),
            terminated=torch.full((4,), term),
            truncated=torch.full((4,), trunc),
        )
        targets[name] = agent.update(batch)["target_q"]
    assert targets["terminated"] == 0.0
    assert targets["truncated"] != 0.0


@pytest.mark.parametrize("algo", ["hydo-cm", "hacman"])
def test_n_step_discount_scales_the_bootstrap(algo):
    """An n-step batch's ``discount`` (γ^m) replaces γ in the target: r + γ^m · V(s')."""
    base = HybridAgent(AgentConfig(algo=algo, **SMALL))
    state = base.state_dict()
    targets = {}
    for discount in (None, 0.99**3, 0.0):
        agent = HybridAgent(AgentConfig(algo=algo, **SMALL))
        agent.load_state_dict(state)
        torch.manual_seed(0)
        d = None if discount is None else torch.full((4,), discount)
        batch = make_batch(4, 16, 16, reward=torch.zeros(4), terminated=torch.zeros(4), discount=d)
        targets[discount] = agent.update(batch)["target_q"]
    assert targets[0.0] == 0.0
    assert targets[0.99**3] == pytest.approx(targets[None] * 0.99**2, rel=1e-4)  # γ is 0.99


@pytest.mark.parametrize("algo", list(ALGOS))
def test_checkpoint_resume_reproduces_next_update(algo, tmp_path):
    cfg = AgentConfig(algo=algo, **SMALL)
    batches = [make_batch(8, 16, 16, seed=s) for s in range(5)]
    agent = HybridAgent(cfg)
    for b in batches[:3]:
        agent.update(b)
    save_checkpoint(tmp_path / "ckpt.pt", {"agent": agent.state_dict()})
    ref = [agent.update(b) for b in batches[3:]]

    resumed = HybridAgent(dataclasses.replace(cfg))  # fresh networks, then the checkpoint
    resumed.load_state_dict(load_checkpoint(tmp_path / "ckpt.pt")["agent"])
    out = [resumed.update(b) for b in batches[3:]]
    assert out == ref  # the same losses, bit for bit
    sd_a, sd_b = agent.state_dict(), resumed.state_dict()
    for key in ("encoder", "critic", "motion_policy", "critic_target"):
        for name, t in sd_a[key].items():
            assert torch.equal(t, sd_b[key][name]), (key, name)
    assert sd_a["n_updates"] == sd_b["n_updates"] == 5
    if agent.is_sac:
        assert torch.equal(sd_a["log_alpha_loc"], sd_b["log_alpha_loc"])


def test_load_refuses_other_config():
    a = HybridAgent(AgentConfig(algo="hydo", **SMALL))
    b = HybridAgent(AgentConfig(algo="hydo-cm", **SMALL))
    with pytest.raises(ValueError, match="different config"):
        b.load_state_dict(a.state_dict())


def diverged_agent(algo: str, **config) -> HybridAgent:
    """An agent whose Polyak-averaged targets differ clearly from its online networks."""
    agent = HybridAgent(AgentConfig(algo=algo, tau=0.5, policy_delay=1, **SMALL, **config))
    for i in range(3):
        agent.update(make_batch(8, 16, 16, seed=i))
    return agent


@pytest.mark.parametrize("algo", ["hacman", "hydo-cm"])
def test_eval_acts_with_the_averaged_weights(algo):
    agent = diverged_agent(algo)
    nets = agent.acting_networks("eval")
    assert nets.encoder is agent.encoder_target and nets.critic is agent.critic_target
    # TD3 has a target motion policy and acts with it; SAC's only motion policy is the online one
    assert nets.motion_policy is (agent.motion_policy_target or agent.motion_policy)
    assert agent.acting_networks("explore").encoder is agent.encoder
    points, features = random_obs(3, 16, 16)

    def q(mode: str) -> torch.Tensor:
        return agent.act(points, features, mode, torch.Generator().manual_seed(0))[2]["q"]

    q_eval, q_explore = q("eval"), q("explore")
    with torch.no_grad():  # a disturbed online encoder moves exploration, not evaluation
        for p in agent.encoder.parameters():
            p.add_(torch.randn_like(p))
    assert torch.equal(q("eval"), q_eval)
    assert not torch.allclose(q("explore"), q_explore)
    agent.config = dataclasses.replace(agent.config, eval_weights="online")
    assert agent.acting_networks("eval").encoder is agent.encoder
    assert not torch.allclose(q("eval"), q_eval)
    with pytest.raises(ValueError, match=r"`eval_weights` must be one of \['average', 'online'\]"):
        AgentConfig(eval_weights="ema")


def test_zero_chain_noise_makes_eval_deterministic_and_exports_so():
    """eval_chain_noise="zero": eval motions no longer depend on the generator, equal the chain run on
    zero noise, and the exported actor ignores its noise input; exploration still samples."""
    agent = HybridAgent(AgentConfig(algo="hydo-cm", eval_chain_noise="zero", **SMALL))
    assert not agent.eval_stochastic
    points, features = random_obs(2, 16, 16, seed=2)
    runs = [agent.act(points, features, "eval", torch.Generator().manual_seed(s)) for s in (0, 1)]
    torch.testing.assert_close(runs[0][2]["motions"], runs[1][2]["motions"])
    f = agent.encoder_target(points, features)
    zero = torch.zeros(agent.motion_policy.noise_shape(2, 16))
    torch.testing.assert_close(runs[0][2]["motions"], agent.motion_policy.sample(f, zero)[0])
    explore = [agent.act(points, features, "explore", torch.Generator().manual_seed(s)) for s in (0, 1)]
    assert not torch.allclose(explore[0][2]["motions"], explore[1][2]["motions"])
    actor = export_modules(agent)["actor"]
    noise = torch.randn(actor.noise_shape(2))
    with torch.no_grad():
        torch.testing.assert_close(actor(f, noise), actor(f, zero))
    assert HybridAgent(AgentConfig(algo="hydo-cm", **SMALL)).eval_stochastic  # the default samples
    with pytest.raises(ValueError, match=r"`eval_chain_noise` must be one of \['sample', 'zero'\]"):
        AgentConfig(eval_chain_noise="mean")


@pytest.mark.parametrize("algo", ["hacman", "hydo-gauss", "hydo-cm"])
def test_export_modules_reproduce_eval_act(algo):
    agent = diverged_agent(algo)  # the export must hold the averaged weights eval acts with
    mods = export_modules(agent)
    points, features = random_obs(3, 16, 16)
    gen = torch.Generator().manual_seed(7)
    index, motion, info = agent.act(points, features, "eval", gen)
    noise = torch.randn(mods["actor"].noise_shape(3), generator=torch.Generator().manual_seed(7))
    with torch.no_grad():
        feats = mods["encoder"](points, features)
        motions = mods["actor"](feats, noise)
        q = mods["critic"](feats, motions)
    q_sel = q.amin(-1) if agent.is_sac else q[..., 0]
    assert torch.equal(q_sel.argmax(-1), index)
    assert torch.allclose(motions[torch.arange(3), index], motion)


def test_act_and_update_with_normals():
    """The default encoder reads the object points' normals: acting needs them and they change Q;
    an update with normals in the batch runs and moves the encoder's normal weights."""
    cfg = AgentConfig(algo="hydo-cm", **{**SMALL, "encoder_normals": True})
    agent = HybridAgent(cfg)
    points, features = random_obs(2, cfg.n_obj, cfg.n_bg)
    g = torch.Generator().manual_seed(0)
    up = torch.nn.functional.normalize(torch.randn(2, cfg.n_obj, 3, generator=g), dim=-1)
    with pytest.raises(ValueError, match="normals"):
        agent.act(points, features, "eval", torch.Generator().manual_seed(0))
    q_up = agent.act(points, features, "eval", torch.Generator().manual_seed(0), normals=up)[2]["q"]
    q_down = agent.act(points, features, "eval", torch.Generator().manual_seed(0), normals=-up)[2]["q"]
    assert not torch.allclose(q_up, q_down)
    before = [p.detach().clone() for p in agent.encoder.parameters()]
    batch = make_batch(4, cfg.n_obj, cfg.n_bg, normals=up.repeat(2, 1, 1), next_normals=up.repeat(2, 1, 1))
    agent.update(batch)
    assert any(not torch.equal(a, b) for a, b in zip(before, agent.encoder.parameters(), strict=True))


def test_bf16_updates_run_in_bf16_and_track_fp32():
    # The trainer's `precision = "bf16"` context: the matmuls run on bf16 inputs (the first update's
    # figures differ from fp32 in their low bits, so autocast took effect) while parameters and
    # optimiser state stay fp32 and the figures stay within bf16's rounding of the fp32 ones.
    from models.perf import PRECISIONS, native_bf16, resolve_precision, update_autocast

    assert resolve_precision("auto") == ("bf16" if native_bf16() else "fp32")
    assert {resolve_precision(p) for p in PRECISIONS} <= {"fp32", "bf16"}
    with pytest.raises(ValueError, match="precision"):
        resolve_precision("fp16")
    cfg = AgentConfig(algo="hydo-cm", **SMALL)
    batches = [make_batch(16, 16, 16, seed=s) for s in range(4)]
    runs = {}
    for precision in ("fp32", "bf16"):
        agent = HybridAgent(cfg)
        with update_autocast(precision):
            runs[precision] = [agent.update(b) for b in batches]
        assert all(p.dtype == torch.float32 for p in agent.critic.parameters())
        assert all(
            v.dtype == torch.float32
            for state in agent.critic_optimizer.state.values()
            for v in state.values()
            if torch.is_tensor(v) and v.is_floating_point()
        )
    fp32, bf16 = runs["fp32"], runs["bf16"]
    assert fp32[0] != bf16[0]
    assert abs(fp32[0]["q"] - bf16[0]["q"]) < 2e-3 and abs(fp32[0]["target_q"] - bf16[0]["target_q"]) < 2e-3
    assert abs(fp32[0]["critic_loss"] - bf16[0]["critic_loss"]) < 0.03 * fp32[0]["critic_loss"]
    assert all(math.isfinite(v) for out in bf16 for v in out.values())
