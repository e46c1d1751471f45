"""The six algorithms as one table of choices, and the hybrid agent that runs any row of it.

Paper: Le et al., "HyDo: Hybrid Diffusion Policy" (reference/hydo-paper.tex §III-C, §IV). Baseline:
Zhou et al., "HACMan" (HACMan-2023/HACMan: ``hacman/algos/hacman_td3.py``, ``location_policy.py``).

=============  ===========  ========  =====================  =====================
``--algo``     paper name   critic    motion policy          entropy
=============  ===========  ========  =====================  =====================
hacman         HACMan       td3       tanh MLP               none (ε-greedy loc.)
hacman-diff    HACMan+Diff  td3       DDPM, K steps          none
hacman-cm      HACMan+CM    td3       consistency, K steps   none
hydo-gauss     HyDo w/o D.  sac       tanh-Gaussian          location + motion
hydo           HyDo         sac       DDPM, K steps          location + chain bound
hydo-cm        HyDo+CM      sac       consistency, K steps   location + chain bound
=============  ===========  ========  =====================  =====================

Everything is per point: the encoder gives features ``f_i`` for the object points, the motion policy
proposes ``a_i`` at every object point, the twin critic scores ``Q(f_i, a_i)``, and the location policy
is ``π_loc(i) = softmax(Q_i / β)`` over object points.

Sharing (one encoder pass per observation per update; DrQ / SAC-AE style):
  * the online encoder encodes s once, with grad; the critic loss alone trains it;
  * the actor reads those features detached (``no_grad``), so actor gradients never move the encoder;
  * s' is encoded once, under ``no_grad``, by the target encoder; both the motion policy (sampling
    a') and the target critic read those features. Using the Polyak-averaged encoder for the policy
    at s' keeps the whole target on slowly moving weights, as the target critic already is.
  * the critic loss only needs the executed point, so the encoder's per-point head runs with grad on
    those B rows and without grad on all object points (for the actor).
"""

from __future__ import annotations

import contextlib
import copy
import math
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, fields
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from models.choices import ALGOS, EVAL_CHAIN_NOISE, EVAL_WEIGHTS, MODES, AlgoSpec
from models.common import check_shape, polyak_update
from models.encoder import PointEncoder
from models.heads import TwinQ, location_policy
from models.motion import (
    CHAIN_ENTROPY,
    MOTION_DIM,
    ConsistencySchedule,
    DDPMSchedule,
    MotionPolicy,
    default_target_entropy,
    make_motion_policy,
)
from models.replay import ReplayBatch

AGENT_FORMAT = "hydo-agent/1"
#: Options that measurements showed do not help (docs/experiments.md), with the value that made them
#: inert. A checkpoint that recorded them at that value loads as before; any other value is refused.
#: (``critic_value_min/max`` only shaped the removed categorical critic's bins.)
REMOVED_OPTIONS: dict[str, Any] = {
    "encoder_knn": 0,
    "critic_layer_norm": False,
    "critic_bins": 0,
    "encoder_local_width": 0.0,
}
REMOVED_INERT = ("critic_value_min", "critic_value_max")


@dataclass(frozen=True)
class AgentConfig:
    """Everything that defines a hybrid agent; recorded with every run and checkpoint."""

    algo: str = "hydo"
    """Which row of the algorithm table (``ALGOS``)."""
    n_obj: int = 128
    """Object points per observation (fixed per model)."""
    n_bg: int = 128
    """Background points per observation (fixed per model)."""
    seed: int = 0
    """Seeds network initialisation and the agent's own update-noise generator."""

    # encoder
    feature_dim: int = 64
    """D, per-point feature size shared by the motion policy and the critic."""
    encoder_hidden: int = 64
    """Width of the encoder's per-point MLPs."""
    encoder_global: int = 64
    """Width of each max-pooled global feature (object, background); 128 costs ~15 % of updates/s."""
    length_scale: float = 0.1
    """Metres per network unit for positions and goal flow inside the encoder."""
    encoder_normals: bool = True
    """The encoder also takes the object points' unit normals (``PointEncoder(normals=True)``; the
    ONNX encoder then has a third input, ``normals``). What a push does depends on the surface the
    fingertip approaches along (the primitive starts at p + 0.04·n), which a PointNet cannot estimate
    from one point: with it and ``critic_motion_dirs=16``, 60-min planar runs reached 78.4 / 81.6 %
    against 62.4 / 67.6 % without (docs/results.md). False in checkpoints made before it was the
    default."""

    # heads
    actor_hidden: int = 64
    """Width of the motion policy / denoiser MLP."""
    critic_hidden: int = 64
    """Width of each Q head."""
    critic_motion_dirs: int = 16
    """k > 0: the Q heads' first layer also gets k bilinear terms ``u_j(f_i) · a`` (learned directions
    from the point's features dotted with the motion, ``heads.TwinQ``); 0: ``[f_i, a]`` only (the
    default before 16 measured better: docs/results.md)."""
    eval_weights: str = "average"
    """Weights that act in ``mode="eval"`` (evaluation, export, deploy): "average", the Polyak-averaged
    target encoder and critic (and TD3's target motion policy; SAC has no target policy, its online one
    proposes), or "online". The average ranks better: on the 60-min planar runs (3 seeds each, the
    same 300 episodes) it lifted every run, hydo-cm from 57.6 % to 61.4 % and hacman from 55.3 % to
    64.3 % (``hydo eval RUNS --episodes 300 --seed 1 --weights online|average``)."""
    eval_chain_noise: str = "sample"
    """How the ddpm / cm chains act in ``mode="eval"`` (evaluation, export, deploy): "sample" (the
    chain's standard-normal noise is the policy, as in the paper; behaviour diversity needs it) or
    "zero" (the noiseless chain: one deterministic motion per point). Exploration always samples;
    tanh and gauss policies are deterministic in eval either way."""

    # motion chains (ddpm / cm)
    denoise_steps: int = 5
    """K, steps of the DDPM or consistency chain."""
    chain_entropy: str = "bound"
    """Motion log-prob estimator of the chains: "bound" (DIME variational bound with the fixed forward
    kernel) or "learned_std" (path density with a learned, bounded per-step std)."""
    final_std: float = 0.05
    """Std of the chain's last step (DDPM σ_1; the consistency model's explicit final Gaussian)."""
    learned_std_min: float = 0.01
    """Lower bound of the per-step std when ``chain_entropy="learned_std"``."""
    learned_std_max: float = 1.0
    """Upper bound of the per-step std when ``chain_entropy="learned_std"``."""
    ddpm_beta_min: float = 0.1
    """VP schedule β_min of the DDPM chain."""
    ddpm_beta_max: float = 10.0
    """VP schedule β_max of the DDPM chain."""
    cm_sigma_max: float = 5.0
    """First noise level T of the consistency chain."""
    cm_sigma_min: float = 0.002
    """Boundary time ε of the consistency function."""
    cm_sigma_data: float = 0.5
    """σ_data of the consistency parameterisation."""
    cm_rho: float = 7.0
    """ρ of the consistency chain's level spacing."""

    # shared RL
    gamma: float = 0.99
    """Discount per primitive."""
    tau: float = 0.005
    """Polyak rate of the target networks."""
    lr_critic: float = 3e-4
    """Adam learning rate of encoder + critic."""
    lr_actor: float = 3e-4
    """Adam learning rate of the motion policy."""
    policy_delay: int | None = 2
    """Critic updates per actor update, for every algorithm (TD3's 2; the measured best setting used
    it for hydo-cm too). None: td3 → 2, sac → 1 (the default before; old checkpoints record it)."""
    actor_points: int | None = 16
    """Points per state differentiated in the actor loss, drawn from π_loc (None = all points, exact
    gradient; m = unbiased estimate after a no-grad scoring pass over all points, see ``update``)."""

    # td3 (HACMan)
    location_beta: float = 0.01
    """Fixed location softmax temperature β of the td3 variants (HACMan's --location_model_temperature).
    Q is in metres of goal flow (per-point Q spreads ~0.01–0.1), so β = 0.1 makes π_loc nearly uniform."""
    epsilon_greedy: float = 0.1
    """Probability of a uniformly random location when exploring (td3; HACMan's --egreedy)."""
    explore_motion_std: float = 0.1
    """Std of the Gaussian noise added to the executed motion when exploring (td3)."""
    target_policy_noise: float = 0.2
    """Std of TD3's target policy smoothing noise."""
    target_noise_clip: float = 0.5
    """Clip of TD3's target policy smoothing noise."""

    # sac (HyDo)
    lr_alpha: float = 3e-3
    """Adam learning rate of the two log-temperatures (3e-4 is too slow to correct a bad initial α
    within the few thousand updates of a short run)."""
    init_alpha_loc: float = 0.01
    """Initial location temperature α_loc (also π_loc's softmax temperature). Sized to the reward
    (metres of goal flow, ~0.05–0.3 per primitive): at 0.1 the location-entropy bonus (0.1 × 4.8 nats)
    outweighs the reward and the cube reached 7 % planar success at 2000 steps; at 0.01, 60 %."""
    init_alpha_motion: float = 0.001
    """Initial motion temperature α_motion (same reasoning; 0.01 made Q positive from entropy alone)."""
    target_entropy_loc: float | None = None
    """Target location entropy in nats (None: ½·log N_obj, i.e. ≈ √N_obj equally likely points)."""
    target_entropy_motion: float | None = None
    """Target of the motion log-prob estimate in nats (None: ``motion.default_target_entropy``: −3 for
    gauss, −3·(1 + log(s_1/final_std)) for the chain bound, −3·K for learned_std)."""

    def __post_init__(self) -> None:
        def check(ok: bool, msg: str) -> None:
            if not ok:
                raise ValueError(msg)

        check(self.algo in ALGOS, f"`algo` must be one of {list(ALGOS)}. Got {self.algo}.")
        check(
            self.eval_weights in EVAL_WEIGHTS,
            f"`eval_weights` must be one of {list(EVAL_WEIGHTS)}. Got {self.eval_weights}.",
        )
        check(
            self.eval_chain_noise in EVAL_CHAIN_NOISE,
            f"`eval_chain_noise` must be one of {list(EVAL_CHAIN_NOISE)}. Got {self.eval_chain_noise}.",
        )
        check(
            self.chain_entropy in CHAIN_ENTROPY,
            f"`chain_entropy` must be one of {list(CHAIN_ENTROPY)}. Got {self.chain_entropy}.",
        )
        check(self.n_obj >= 1, f"`n_obj` must be ≥ 1. Got {self.n_obj}.")
        check(self.n_bg >= 0, f"`n_bg` must be ≥ 0. Got {self.n_bg}.")
        check(self.denoise_steps >= 1, f"`denoise_steps` must be ≥ 1. Got {self.denoise_steps}.")
        check(0 < self.gamma <= 1, f"`gamma` must be in (0, 1]. Got {self.gamma}.")
        check(0 < self.tau <= 1, f"`tau` must be in (0, 1]. Got {self.tau}.")
        check(
            0 <= self.epsilon_greedy <= 1, f"`epsilon_greedy` must be in [0, 1]. Got {self.epsilon_greedy}."
        )
        check(self.location_beta > 0, f"`location_beta` must be > 0. Got {self.location_beta}.")
        check(self.init_alpha_loc > 0, f"`init_alpha_loc` must be > 0. Got {self.init_alpha_loc}.")
        check(self.init_alpha_motion > 0, f"`init_alpha_motion` must be > 0. Got {self.init_alpha_motion}.")
        check(
            self.policy_delay is None or self.policy_delay >= 1,
            f"`policy_delay` must be None or ≥ 1. Got {self.policy_delay}.",
        )
        check(
            self.actor_points is None or self.actor_points >= 1,
            f"`actor_points` must be None or ≥ 1. Got {self.actor_points}.",
        )
        check(
            self.critic_motion_dirs >= 0, f"`critic_motion_dirs` must be ≥ 0. Got {self.critic_motion_dirs}."
        )
        # Rates, scales and noise levels: a zero or negative one trains nothing or divides by zero.
        for name in (
            "length_scale",
            "final_std",
            "lr_critic",
            "lr_actor",
            "lr_alpha",
            "cm_sigma_data",
            "cm_rho",
            "ddpm_beta_min",
            "cm_sigma_min",
        ):
            check(getattr(self, name) > 0, f"`{name}` must be > 0. Got {getattr(self, name)}.")
        for name in ("explore_motion_std", "target_policy_noise", "target_noise_clip"):
            check(getattr(self, name) >= 0, f"`{name}` must be ≥ 0. Got {getattr(self, name)}.")
        for low, high in (
            ("learned_std_min", "learned_std_max"),
            ("ddpm_beta_min", "ddpm_beta_max"),
            ("cm_sigma_min", "cm_sigma_max"),
        ):
            check(
                0 < getattr(self, low) < getattr(self, high),
                f"`{low}` must be > 0 and below `{high}`. Got {getattr(self, low)}, {getattr(self, high)}.",
            )
        for name in ("feature_dim", "encoder_hidden", "encoder_global", "actor_hidden", "critic_hidden"):
            check(getattr(self, name) >= 1, f"`{name}` must be ≥ 1. Got {getattr(self, name)}.")

    @property
    def spec(self) -> AlgoSpec:
        """The algorithm table row of ``algo``."""
        return ALGOS[self.algo]

    @property
    def resolved_policy_delay(self) -> int:
        """``policy_delay`` with the objective's default filled in."""
        if self.policy_delay is not None:
            return self.policy_delay
        return 2 if self.spec.objective == "td3" else 1

    @property
    def resolved_target_entropy_loc(self) -> float:
        """``target_entropy_loc`` with the default ½·log N_obj filled in."""
        if self.target_entropy_loc is not None:
            return self.target_entropy_loc
        return 0.5 * math.log(self.n_obj)

    @property
    def resolved_target_entropy_motion(self) -> float:
        """``target_entropy_motion`` with the motion policy's default filled in."""
        if self.target_entropy_motion is not None:
            return self.target_entropy_motion
        return default_target_entropy(
            self.spec.motion, self.chain_entropy, self.ddpm_schedule(), self.cm_schedule()
        )

    def ddpm_schedule(self) -> DDPMSchedule:
        """The DDPM noise schedule these fields describe."""
        return DDPMSchedule(
            n_steps=self.denoise_steps,
            beta_min=self.ddpm_beta_min,
            beta_max=self.ddpm_beta_max,
            final_std=self.final_std,
        )

    def cm_schedule(self) -> ConsistencySchedule:
        """The consistency sampler's schedule these fields describe."""
        return ConsistencySchedule(
            n_steps=self.denoise_steps,
            sigma_max=self.cm_sigma_max,
            sigma_min=self.cm_sigma_min,
            final_std=self.final_std,
            sigma_data=self.cm_sigma_data,
            rho=self.cm_rho,
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain dict of the fields plus the resolved defaults and the table row (for run records)."""
        d = asdict(self)
        d["resolved"] = {
            "policy_delay": self.resolved_policy_delay,
            "target_entropy_loc": self.resolved_target_entropy_loc,
            "target_entropy_motion": self.resolved_target_entropy_motion,
            **asdict(self.spec),
        }
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> AgentConfig:
        """Inverse of :meth:`to_dict` (ignores the ``resolved`` record)."""
        names = {f.name for f in fields(cls)}
        for key, inert in REMOVED_OPTIONS.items():
            if key in d and d[key] != inert:
                raise ValueError(
                    f"`{key}` = {d[key]!r} was removed from hydo (docs/experiments.md); "
                    "this checkpoint needs the version that made it"
                )
        d = {k: v for k, v in d.items() if k not in REMOVED_OPTIONS and k not in REMOVED_INERT}
        unknown = set(d) - names - {"resolved"}
        if unknown:
            raise ValueError(f"unknown AgentConfig fields: {sorted(unknown)}")
        return cls(**{k: v for k, v in d.items() if k in names})


@contextlib.contextmanager
def frozen(module: nn.Module) -> Iterator[None]:
    """Stop gradients into ``module``'s parameters (they still flow to its inputs).

    The actor loss differentiates the critic w.r.t. the actions only; without this, backward would
    also compute (and then discard) every critic weight gradient.
    """
    params = [p for p in module.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


class SurrogateWeights(NamedTuple):
    """Per-point quantities of the actor objective, computed without grad."""

    coef: torch.Tensor  # (B, N_obj) c_i, the weight of ∇Q_i in the actor gradient
    loss: torch.Tensor  # (B,) Σ_i π_loc(i) J_i, the actor loss value per state


def actor_surrogate_weights(
    q: torch.Tensor,
    log_prob: torch.Tensor,
    alpha_loc: torch.Tensor | float,
    alpha_motion: torch.Tensor | float,
    sac: bool,
) -> SurrogateWeights:
    """Weights of the unbiased point-subset estimator of the actor gradient.

    ``q (B, N)`` the actor's Q at each point's sampled motion, ``log_prob (B, N)`` its log-prob
    estimate, β = ``alpha_loc`` the location temperature. With ``π = softmax(Q/β)`` and
    ``J_i = −Q_i + β log π_i + α_m log π_m,i`` (SAC; ``−Q_i`` for TD3), ``L = Σ_i π_i J_i`` has

        ∇L = Σ_i ∇π_i J_i + Σ_i π_i ∇J_i
           = Σ_i π_i [ (J_i − J̄)/β · ∇Q_i − ∇Q_i + α_m ∇log π_m,i ]        (J̄ = Σ_j π_j J_j)

    using ``∇π_i = π_i (∇Q_i − Σ_j π_j ∇Q_j)/β`` and ``Σ_i π_i ∇log π_i = 0``. So for i ∼ π the
    surrogate ``c_i Q_i + α_m log π_m,i`` with ``c_i = (J_i − J̄)/β − 1`` held constant has expected
    gradient ∇L: differentiating m points drawn from π_loc is an unbiased estimate.
    """
    pi, log_pi = location_policy(q, alpha_loc)  # (B, N)
    j = -q + alpha_loc * log_pi + alpha_motion * log_prob if sac else -q  # (B, N)
    j_bar = (pi * j).sum(-1, keepdim=True)  # (B, 1)
    return SurrogateWeights(coef=(j - j_bar) / alpha_loc - 1.0, loss=j_bar.squeeze(-1))


class ActingNetworks(NamedTuple):
    """The three networks behind a decision (and behind the ONNX interface)."""

    encoder: PointEncoder
    motion_policy: MotionPolicy
    critic: TwinQ


class HybridAgent:
    """Hybrid location/motion actor-critic for any row of ``ALGOS``.

    Observations: ``points (B, N, 3)`` float32 metres (world frame, object points first, N = n_obj +
    n_bg) and ``features (B, N, 4)`` ``[is_object, goal_flow_xyz (m)]``. Actions: ``index (B,)`` int64
    into the object points and ``motion (B, 3)`` in [-1, 1].
    """

    def __init__(self, config: AgentConfig) -> None:
        self.config = config
        spec = config.spec
        self.spec = spec
        self.is_sac = spec.objective == "sac"
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(config.seed)
            self.encoder = PointEncoder(
                config.n_obj,
                config.n_bg,
                out_dim=config.feature_dim,
                hidden=config.encoder_hidden,
                global_dim=config.encoder_global,
                length_scale=config.length_scale,
                normals=config.encoder_normals,
            )
            self.critic = TwinQ(
                config.feature_dim,
                config.critic_hidden,
                motion_dirs=config.critic_motion_dirs,
            )
            self.motion_policy: MotionPolicy = make_motion_policy(
                spec.motion,
                config.feature_dim,
                config.actor_hidden,
                entropy=config.chain_entropy,
                std_min=config.learned_std_min,
                std_max=config.learned_std_max,
                ddpm=config.ddpm_schedule(),
                cm=config.cm_schedule(),
            )
        self.encoder_target = copy.deepcopy(self.encoder).requires_grad_(False)
        self.critic_target = copy.deepcopy(self.critic).requires_grad_(False)
        # TD3 keeps a target policy; SAC samples the current policy at s'.
        self.motion_policy_target = (
            None if self.is_sac else copy.deepcopy(self.motion_policy).requires_grad_(False)
        )
        self.critic_optimizer = torch.optim.Adam(
            [*self.encoder.parameters(), *self.critic.parameters()], lr=config.lr_critic, fused=True
        )
        self.actor_optimizer = torch.optim.Adam(
            self.motion_policy.parameters(), lr=config.lr_actor, fused=True
        )
        if self.is_sac:
            self.log_alpha_loc = torch.tensor(math.log(config.init_alpha_loc), requires_grad=True)
            self.log_alpha_motion = torch.tensor(math.log(config.init_alpha_motion), requires_grad=True)
            self.alpha_optimizer: torch.optim.Optimizer | None = torch.optim.Adam(
                [self.log_alpha_loc, self.log_alpha_motion], lr=config.lr_alpha, fused=True
            )
        else:
            self.alpha_optimizer = None
        self.n_updates = 0
        self.generator = torch.Generator().manual_seed(config.seed + 1)  # update noise only
        #: Called on each optimiser's parameters between backward and step. Data-parallel training
        #: (``hydo_cli.trainer`` with ``workers > 1``) sets it to average the gradients over the
        #: workers' half-batches, so every replica takes the same step on the full batch.
        self.sync_gradients: Callable[[list[torch.Tensor]], None] | None = None

    # ------------------------------------------------------------------ helpers
    def _step(self, *steps: tuple[torch.optim.Optimizer, torch.Tensor]) -> None:
        """For each ``(optimizer, loss)``: zero_grad → backward; then one gradient sync across the
        data-parallel workers for all of them; then every step. The losses must not depend on each
        other's parameters (actor and temperature losses do not: the latter read detached values)."""
        for optimizer, loss in steps:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
        if self.sync_gradients is not None:
            self.sync_gradients([p for opt, _ in steps for g in opt.param_groups for p in g["params"]])
        for optimizer, _ in steps:
            optimizer.step()

    def _randn(self, *shape: int) -> torch.Tensor:
        return torch.randn(shape, generator=self.generator)

    @property
    def alpha_loc(self) -> float:
        """Current location temperature (SAC) or the fixed β (TD3)."""
        return self.log_alpha_loc.exp().item() if self.is_sac else self.config.location_beta

    @property
    def alpha_motion(self) -> float:
        """Current motion temperature (SAC; 0 for TD3)."""
        return self.log_alpha_motion.exp().item() if self.is_sac else 0.0

    def num_parameters(self) -> int:
        """Trainable parameters of encoder, critic and motion policy (targets excluded)."""
        mods = (self.encoder, self.critic, self.motion_policy)
        return sum(p.numel() for m in mods for p in m.parameters())

    def _check_obs(self, points: torch.Tensor, features: torch.Tensor) -> None:
        n = self.config.n_obj + self.config.n_bg
        check_shape("points", points, (None, n, 3), torch.float32)
        check_shape("features", features, (points.shape[0], n, 4), torch.float32)

    # ------------------------------------------------------------------ acting
    def acting_networks(self, mode: str) -> ActingNetworks:
        """The networks that act in ``mode``: exploration always uses the online ones (the data then
        follows what the critic is learning); evaluation uses the Polyak-averaged targets when
        ``config.eval_weights == "average"``. Export and deploy take ``acting_networks("eval")``, so
        an exported model decides exactly as ``hydo eval`` of its run."""
        if mode not in MODES:
            raise ValueError(f"`mode` must be one of {list(MODES)}. Got {mode}.")
        if mode == "eval" and self.config.eval_weights == "average":
            motion = (
                self.motion_policy_target if self.motion_policy_target is not None else self.motion_policy
            )
            return ActingNetworks(self.encoder_target, motion, self.critic_target)
        return ActingNetworks(self.encoder, self.motion_policy, self.critic)

    @property
    def eval_stochastic(self) -> bool:
        """Whether ``act(mode="eval")`` (and so an export of this agent) samples its motions: the
        chains with ``eval_chain_noise == "sample"``; never tanh / gauss."""
        return self.motion_policy.stochastic_eval and self.config.eval_chain_noise == "sample"

    def decision_q(self, q_twin: torch.Tensor) -> torch.Tensor:
        """The Q a location is chosen on, from twin Q ``(..., 2)``: the twin minimum (SAC) or Q1 (TD3,
        as HACMan). ``(...)``; export records the same choice as the manifest's ``q_reduction``."""
        return q_twin.amin(-1) if self.is_sac else q_twin[..., 0]

    @torch.no_grad()
    def act(
        self,
        points: torch.Tensor,
        features: torch.Tensor,
        mode: str = "explore",
        generator: torch.Generator | None = None,
        normals: torch.Tensor | None = None,
        feasible: Callable[[np.ndarray], np.ndarray] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, dict[str, torch.Tensor]]:
        """Choose ``(index (B,) int64, motion (B, 3) in [-1, 1])`` for a batch of observations.

        ``points (B, N, 3)`` float32 metres, ``features (B, N, 4)``. ``mode``:

        * ``"explore"``: location sampled from π_loc = softmax(Q / β) (SAC: β = α_loc; TD3: β =
          ``location_beta`` and, with probability ``epsilon_greedy``, a uniform location, as HACMan);
          motion sampled from the policy (TD3: plus Gaussian noise ``explore_motion_std``).
        * ``"eval"``: location = argmax of Q over object points; motion from the policy without
          exploration noise. Deterministic for tanh and gauss (``tanh(mean)``); **stochastic for ddpm
          and cm** with ``eval_chain_noise="sample"``: the chain's noise is the policy (as in the
          paper's real-robot runs; pass a seeded ``generator`` to reproduce it); with "zero" the chain
          runs on zero noise. Acts with ``acting_networks("eval")`` (by default the
          Polyak-averaged encoder and critic).

        Q at each point is scored on the motion proposed at that point (TD3: Q1, as HACMan; SAC: the
        twin minimum). ``feasible`` is the feasibility mask, made by the caller where the observation
        is made (``sim.primitive.feasibility_mask``): a function of the motions proposed at the object
        points ``(B, N_obj, 3)`` → ``bool (B, N_obj)``; the location is then chosen among the points
        whose push can run. None: among all object points. An encoder with ``encoder_normals`` needs
        the object points' unit ``normals (B, N_obj, 3)``. ``info``: ``q (B, N_obj)`` (unmasked), ``q_select (B, N_obj)`` (the Q the
        location is chosen on: −inf at infeasible points), ``location_probs (B, N_obj)``,
        ``motions (B, N_obj, 3)``, ``motion_log_prob (B,)`` (log-prob estimate of the chosen point's
        motion).
        """
        self._check_obs(points, features)
        cfg = self.config
        nets = self.acting_networks(mode)
        f = nets.encoder(points, features, normals)  # (B, N_obj, D)
        b, n = f.shape[:2]
        noise = torch.randn(nets.motion_policy.noise_shape(b, n), generator=generator)
        deterministic = mode == "eval" and not self.eval_stochastic
        motions, log_prob = nets.motion_policy.sample(f, noise, deterministic=deterministic)  # (B, N_obj, 3)
        q_twin = nets.critic(f, motions)  # (B, N_obj, 2)
        q = self.decision_q(q_twin)  # (B, N_obj)
        q_select = q
        if feasible is not None:
            allowed = torch.from_numpy(np.asarray(feasible(motions.numpy()), dtype=bool))  # (B, N_obj)
            q_select = q.masked_fill(~allowed, -math.inf)
        probs, _ = location_policy(q_select, self.alpha_loc)  # (B, N_obj)
        if mode == "eval":
            index = q_select.argmax(-1)  # (B,)
        else:
            index = torch.multinomial(probs, 1, generator=generator).squeeze(-1)  # (B,)
            if not self.is_sac and cfg.epsilon_greedy > 0:
                allowed = torch.isfinite(q_select).to(q.dtype)  # uniform over the feasible points
                uniform = torch.multinomial(allowed, 1, generator=generator).squeeze(-1)
                explore_uniform = torch.rand(b, generator=generator) < cfg.epsilon_greedy
                index = torch.where(explore_uniform, uniform, index)
        rows = torch.arange(b)
        motion = motions[rows, index]  # (B, 3)
        if mode == "explore" and not self.is_sac and cfg.explore_motion_std > 0:
            motion = (motion + cfg.explore_motion_std * torch.randn(b, 3, generator=generator)).clamp(-1, 1)
        info = {
            "q": q,
            "q_select": q_select,
            "location_probs": probs,
            "motions": motions,
            "motion_log_prob": log_prob[rows, index],
        }
        return index, motion, info

    # ------------------------------------------------------------------ learning
    def update(self, batch: ReplayBatch) -> dict[str, float]:
        """One gradient update (critic; actor and temperatures every ``policy_delay``; Polyak).

        ``batch``: a :class:`~models.replay.ReplayBatch` (float32 tensors; see its fields for shapes).
        Returns scalar diagnostics. Only ``terminated`` masks the bootstrap: a truncated transition
        (primitive cap) still bootstraps from its real next observation.

        Actor loss ``L = mean_s Σ_i π_loc(i) J_i`` over the object points, with
        ``J_i = −Q_i + α_loc log π_loc(i) + α_motion log π_m(a_i)`` (SAC) or ``J_i = −Q1_i`` (TD3) and
        the gradient through the softmax. With ``actor_points = m`` it is estimated without bias:
        every point is scored without grad (chain + critic, forward only), then m points are drawn
        from π_loc and only they are differentiated, using ``∇L = E_{i∼π_loc}[c_i ∇Q_i + α_motion ∇log
        π_m(a_i)]`` with ``c_i = (J_i − Σ_j π_j J_j)/β − 1`` (see :func:`actor_surrogate_weights`).
        """
        cfg = self.config
        self._check_obs(batch.points, batch.features)
        self._check_obs(batch.next_points, batch.next_features)
        b = batch.reward.shape[0]
        check_shape("index", batch.index, (b,), torch.int64)
        check_shape("motion", batch.motion, (b, MOTION_DIM))
        for name in ("reward", "terminated", "truncated"):
            check_shape(name, getattr(batch, name), (b,))
        rows = torch.arange(b)
        n_obj = cfg.n_obj
        self.n_updates += 1
        actor_step = self.n_updates % cfg.resolved_policy_delay == 0
        subset = actor_step and cfg.actor_points is not None
        alpha_loc = self.log_alpha_loc.exp().detach() if self.is_sac else cfg.location_beta
        alpha_m = self.log_alpha_motion.exp().detach() if self.is_sac else 0.0
        noise_shape = self.motion_policy.noise_shape
        out: dict[str, float] = {}

        # 1. Encode s once. Only the executed points' features carry grad, and only the rows that
        #    gradient can reach are differentiated (``encode_for_update``: exact); every object
        #    point's features are computed without grad for the actor.
        f_taken, ctx = self.encoder.encode_for_update(
            batch.points, batch.features, batch.normals, batch.index
        )  # (B, D) with grad; detached local (B, N_obj, H), context (B, H)
        with torch.no_grad():  # (B, N_obj, D), detached; only the actor reads it
            f_obj = self.encoder.head(ctx.local, ctx.context[:, None]) if actor_step else None
        noise_s = self._randn(*noise_shape(b, n_obj)) if actor_step else None  # (B, N_obj, S, 3)

        # 2. Target: exact expectation over all object points of s' and a motion sampled at each.
        with torch.no_grad():
            f_next = self.encoder_target(
                batch.next_points, batch.next_features, batch.next_normals
            )  # (B, N_obj, D)
            noise_next = self._randn(*noise_shape(b, n_obj))  # (B, N_obj, S, 3)
            if self.is_sac:
                # One chain call samples a' at s' and, when the actor is scored below, a at s.
                if subset:
                    a_all, logp_all = self.motion_policy.sample(
                        torch.cat([f_next, f_obj]), torch.cat([noise_next, noise_s])
                    )  # (2B, N_obj, 3), (2B, N_obj)
                    a_next, logp_next, a_s, logp_s = a_all[:b], logp_all[:b], a_all[b:], logp_all[b:]
                else:  # a' (B, N_obj, 3), log π_m(a') (B, N_obj)
                    a_next, logp_next = self.motion_policy.sample(f_next, noise_next)
                q_next = self.critic_target(f_next, a_next).amin(-1)  # (B, N_obj): twin min
                pi_next, log_pi_next = location_policy(q_next, alpha_loc)  # (B, N_obj)
                soft_q = q_next - alpha_loc * log_pi_next - alpha_m * logp_next  # (B, N_obj)
            else:
                a_next, _ = self.motion_policy_target.sample(f_next, noise_next)  # (B, N_obj, 3)
                smoothing = (self._randn(b, n_obj, MOTION_DIM) * cfg.target_policy_noise).clamp(
                    -cfg.target_noise_clip, cfg.target_noise_clip
                )
                a_next = (a_next + smoothing).clamp(-1.0, 1.0)  # TD3 target policy smoothing
                q_next = self.critic_target(f_next, a_next).amin(-1)  # (B, N_obj)
                pi_next, _ = location_policy(q_next, alpha_loc)  # (B, N_obj), HACMan's fixed β
                soft_q = q_next
                if subset:
                    a_s, logp_s = self.motion_policy.sample(f_obj, noise_s)  # (B, N_obj, 3), (B, N_obj)
            v_next = (pi_next * soft_q).sum(-1)  # (B,)
            discount = cfg.gamma if batch.discount is None else batch.discount  # γ, or γ^m (n-step)
            target_q = batch.reward + discount * (1.0 - batch.terminated) * v_next  # (B,)

        # 3. Critic loss on the executed (index, motion); trains encoder + critic.
        q_taken = self.critic(f_taken, batch.motion)  # (B, 2)
        critic_loss = F.mse_loss(q_taken[:, 0], target_q) + F.mse_loss(q_taken[:, 1], target_q)
        self._step((self.critic_optimizer, critic_loss))
        out.update(critic_loss=critic_loss.item(), q=q_taken.mean().item(), target_q=target_q.mean().item())

        if actor_step:
            # 4. Actor: L = mean_s Σ_i π_loc(i) J_i, gradient through the softmax (paper §III-C).
            if subset:
                # 4a. Score every object point without grad (with the just-updated critic).
                with torch.no_grad():
                    q_s = self._actor_q(f_obj, a_s)  # (B, N_obj)
                    pi, log_pi = location_policy(q_s, alpha_loc)  # (B, N_obj)
                    logp = logp_s
                    weights = actor_surrogate_weights(q_s, logp_s, alpha_loc, alpha_m, self.is_sac)
                    # 4b. Differentiate m points drawn from π_loc (with replacement).
                    pick = torch.multinomial(pi, cfg.actor_points, replacement=True, generator=self.generator)
                    coef = weights.coef.gather(1, pick)  # (B, m)
                f_sub = f_obj[rows[:, None], pick]  # (B, m, D)
                with frozen(self.critic):
                    a_sub, logp_sub = self.motion_policy.sample(
                        f_sub, noise_s[rows[:, None], pick]
                    )  # (B, m, 3)
                    q_sub = self._actor_q(f_sub, a_sub)  # (B, m)
                    actor_loss = (coef * q_sub + alpha_m * logp_sub).mean(-1).mean()  # the surrogate
                out["actor_loss"] = weights.loss.mean().item()
            else:
                with frozen(self.critic):
                    a, logp = self.motion_policy.sample(f_obj, noise_s)  # (B, N_obj, 3), (B, N_obj)
                    q = self._actor_q(f_obj, a)  # (B, N_obj)
                    pi, log_pi = location_policy(q, alpha_loc)  # (B, N_obj)
                    j = -q + alpha_loc * log_pi + alpha_m * logp if self.is_sac else -q  # (B, N_obj) J_i
                    actor_loss = (pi * j).sum(-1).mean()
                out["actor_loss"] = actor_loss.item()
                pi, log_pi, logp = pi.detach(), log_pi.detach(), logp.detach()

            # 5. Temperatures (SAC): log-α losses on detached entropy estimates, as SB3 / CleanRL;
            #    stepped together with the actor (one gradient sync for both).
            steps = [(self.actor_optimizer, actor_loss)]
            if self.is_sac:
                entropy_loc = -(pi * log_pi).sum(-1)  # (B,) exact location entropy
                entropy_motion = -(pi * logp).sum(-1)  # (B,) motion entropy (estimate) where π_loc picks
                alpha_loss = self.log_alpha_loc * (entropy_loc - cfg.resolved_target_entropy_loc).mean()
                alpha_loss = (
                    alpha_loss
                    + self.log_alpha_motion * (entropy_motion - cfg.resolved_target_entropy_motion).mean()
                )
                steps.append((self.alpha_optimizer, alpha_loss))
            self._step(*steps)
            if self.is_sac:
                out.update(
                    entropy_loc=entropy_loc.mean().item(),
                    entropy_motion=entropy_motion.mean().item(),
                    alpha_loc=self.alpha_loc,
                    alpha_motion=self.alpha_motion,
                )

        # 6. Polyak: SAC every update; TD3 with the (delayed) actor, as TD3 / SB3.
        if self.is_sac or actor_step:
            polyak_update(self.encoder.parameters(), self.encoder_target.parameters(), cfg.tau)
            polyak_update(self.critic.parameters(), self.critic_target.parameters(), cfg.tau)
            if self.motion_policy_target is not None:
                polyak_update(
                    self.motion_policy.parameters(), self.motion_policy_target.parameters(), cfg.tau
                )
        return out

    def _actor_q(self, f: torch.Tensor, a: torch.Tensor) -> torch.Tensor:
        """Q the actor maximises: twin minimum (SAC, as CleanRL) or Q1 (TD3 / HACMan). ``(B, M)``."""
        return self.critic(f, a).amin(-1) if self.is_sac else self.critic.q1(f, a)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict[str, Any]:
        """Networks, targets, optimisers, log-temperatures, update counter, RNG state and config."""
        sd: dict[str, Any] = {
            "format": AGENT_FORMAT,
            "config": self.config.to_dict(),
            "n_updates": self.n_updates,
            "generator": self.generator.get_state(),
            "encoder": self.encoder.state_dict(),
            "critic": self.critic.state_dict(),
            "motion_policy": self.motion_policy.state_dict(),
            "encoder_target": self.encoder_target.state_dict(),
            "critic_target": self.critic_target.state_dict(),
            "critic_optimizer": self.critic_optimizer.state_dict(),
            "actor_optimizer": self.actor_optimizer.state_dict(),
        }
        if self.motion_policy_target is not None:
            sd["motion_policy_target"] = self.motion_policy_target.state_dict()
        if self.is_sac:
            sd["log_alpha_loc"] = self.log_alpha_loc.detach().clone()
            sd["log_alpha_motion"] = self.log_alpha_motion.detach().clone()
            sd["alpha_optimizer"] = self.alpha_optimizer.state_dict()
        return sd

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Restore everything :meth:`state_dict` saved; refuses a different config."""
        if sd.get("format") != AGENT_FORMAT:
            raise ValueError(f"agent state has format {sd.get('format')!r}, expected {AGENT_FORMAT!r}")
        saved = AgentConfig.from_dict(sd["config"])
        if saved != self.config:
            diff = {
                k: (v, getattr(self.config, k))
                for k, v in asdict(saved).items()
                if getattr(self.config, k) != v
            }
            raise ValueError(f"agent state was saved with a different config (saved, current): {diff}")
        sd = self._drop_inert_layer_norm(sd)
        self.encoder.load_state_dict(sd["encoder"])
        self.critic.load_state_dict(sd["critic"])
        self.motion_policy.load_state_dict(sd["motion_policy"])
        self.encoder_target.load_state_dict(sd["encoder_target"])
        self.critic_target.load_state_dict(sd["critic_target"])
        self.critic_optimizer.load_state_dict(sd["critic_optimizer"])
        self.actor_optimizer.load_state_dict(sd["actor_optimizer"])
        if self.motion_policy_target is not None:
            self.motion_policy_target.load_state_dict(sd["motion_policy_target"])
        if self.is_sac:
            with torch.no_grad():
                self.log_alpha_loc.copy_(sd["log_alpha_loc"])
                self.log_alpha_motion.copy_(sd["log_alpha_motion"])
            self.alpha_optimizer.load_state_dict(sd["alpha_optimizer"])
        self.n_updates = int(sd["n_updates"])
        self.generator.set_state(sd["generator"])

    def _drop_inert_layer_norm(self, sd: dict[str, Any]) -> dict[str, Any]:
        """Checkpoints made before the Q-head LayerNorm option was removed hold its never-used
        parameters (``ln_weight``, ``ln_bias``: no gradient, no optimiser state). Drop them from the
        critic's state dicts and renumber the critic optimiser's parameters to match."""
        keys = list(sd["critic"])
        if "ln_weight" not in keys:
            return sd
        sd = dict(sd)
        n_enc = len(list(self.encoder.parameters()))
        drop = {n_enc + keys.index("ln_weight"), n_enc + keys.index("ln_bias")}
        for name in ("critic", "critic_target"):
            sd[name] = {k: v for k, v in sd[name].items() if k not in ("ln_weight", "ln_bias")}
        opt = sd["critic_optimizer"]
        (group,) = opt["param_groups"]
        new_id = {old: new for new, old in enumerate(i for i in group["params"] if i not in drop)}
        sd["critic_optimizer"] = {
            "state": {new_id[i]: v for i, v in opt["state"].items() if i not in drop},
            "param_groups": [{**group, "params": list(range(len(new_id)))}],
        }
        return sd

    @classmethod
    def from_state_dict(cls, sd: dict[str, Any]) -> HybridAgent:
        """Build an agent from a saved state (its config included) and load it."""
        agent = cls(AgentConfig.from_dict(sd["config"]))
        agent.load_state_dict(sd)
        return agent
