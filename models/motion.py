"""Per-point motion policies behind one interface: tanh (TD3), tanh-Gaussian, DDPM and consistency.

Every policy maps per-point features ``f (B, M, D)`` and an explicit standard-normal ``noise`` of shape
``noise_shape(B, M) = (B, M, S, 3)`` to ``(motion (B, M, 3) in [-1, 1], log_prob (B, M))``::

    motion, log_prob = policy.sample(f, noise)                # training, acting and ONNX export alike
    motion, _ = policy.sample(f, torch.zeros(policy.noise_shape(B, M)))   # fixed noise → fixed result

Training, the unrolled-K ONNX actor and the parity tests all call this same ``sample``; nothing is
drawn inside it, so a fixed ``noise`` gives bit-identical results and the exported graph takes the
noise as an input.

Diffusion / consistency chains run in an unsquashed space ``u`` and the motion is ``tanh(u)``; their
``log_prob`` is an *estimate* (see ``ChainEntropy``) plus the tanh change-of-variables term.

ChainEntropy (``entropy=`` of :class:`DDPMPolicy` and :class:`ConsistencyPolicy`):
    With a fixed per-step variance, ``Σ_k log p_θ(u^{k−1} | u^k)`` evaluated on a reparameterised
    sample is a constant (``−½‖z‖² − log σ_k``), so its gradient is zero and an entropy bonus built
    from it does nothing. Two estimators that do depend on θ:

    ``"bound"`` (default; DIME, ALRhub/DIME): with the fixed forward (noising) kernel q,
        ``log π̂(u^0) = log p(u^K) + Σ_k [log p_θ(u^{k−1} | u^k) − log q(u^k | u^{k−1})]``.
        ``E[log π̂] = E[log π(u^0)] + KL(p(u^{1:K} | u^0) ‖ q(u^{1:K} | u^0)) ≥ −H(π)``, so
        ``−E[log π̂]`` is a lower bound on the entropy, and the q terms carry the gradient through
        the sampled chain (they push the reverse chain to keep the information in its noise).
    ``"learned_std"``: the per-step standard deviation is a bounded output of the denoiser,
        ``σ ∈ [std_min, std_max]`` (sigmoid-scaled in log space), and ``log π̂`` is the paper's path
        density ``log p(u^K) + Σ_k log p_θ(u^{k−1} | u^k)``, which then depends on θ through σ.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from models.common import LOG_2PI, check_shape, mlp, tanh_log_det

MOTION_DIM = 3
CHAIN_ENTROPY = ("bound", "learned_std")


class MotionPolicy(nn.Module):
    """Interface shared by the four motion policies (see the module docstring)."""

    #: ``"tanh" | "gauss" | "ddpm" | "cm"``.
    kind: str = ""
    #: Whether ``act(mode="eval")`` samples (True for the chains) or uses the deterministic mode.
    stochastic_eval: bool = False
    #: Standard-normal draws per point (the S in ``noise_shape``).
    n_noise: int = 1

    def noise_shape(self, batch: int, n_points: int) -> tuple[int, int, int, int]:
        """Shape ``(B, M, S, 3)`` of the standard-normal ``noise`` that ``sample`` consumes."""
        return (batch, n_points, self.n_noise, MOTION_DIM)

    def sample(
        self, f: torch.Tensor, noise: torch.Tensor, deterministic: bool = False
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """``f (B, M, D)``, ``noise (B, M, S, 3)`` → ``motion (B, M, 3)`` in [-1, 1], ``log_prob (B, M)``.

        ``deterministic=True`` returns the policy's deterministic action where it has one (tanh: always;
        gauss: ``tanh(mean)``); for the chains it is the zero-noise chain, which is *not* the mode of
        the distribution.
        """
        raise NotImplementedError

    def _check(self, f: torch.Tensor, noise: torch.Tensor) -> tuple[int, int]:
        b, m = f.shape[0], f.shape[1]
        check_shape("noise", noise, self.noise_shape(b, m))
        return b, m


class TanhPolicy(MotionPolicy):
    """Deterministic ``tanh(MLP(f))`` (HACMan / TD3). ``noise`` is accepted and ignored, so every
    policy has the same signature; ``log_prob`` is zeros. Exploration noise is the algorithm's job."""

    kind = "tanh"

    def __init__(self, feature_dim: int, hidden: int = 64) -> None:
        super().__init__()
        self.net = mlp([feature_dim, hidden, hidden, MOTION_DIM])

    def sample(self, f, noise, deterministic=False):
        self._check(f, noise)
        motion = torch.tanh(self.net(f))  # (B, M, 3)
        return motion, torch.zeros(motion.shape[:-1], dtype=f.dtype, device=f.device)


class GaussPolicy(MotionPolicy):
    """Tanh-squashed diagonal Gaussian (SAC): ``u = μ + σ·z``, ``motion = tanh(u)``.

    ``log π(a) = log N(u; μ, σ²) − Σ log(1 − tanh²u)`` (change of variables, see ``tanh_log_det``).
    ``log σ`` is tanh-scaled into [-5, 2] (CleanRL's bounds) so it cannot run away.
    """

    kind = "gauss"
    LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0

    def __init__(self, feature_dim: int, hidden: int = 64) -> None:
        super().__init__()
        self.net = mlp([feature_dim, hidden, hidden, 2 * MOTION_DIM])

    def sample(self, f, noise, deterministic=False):
        self._check(f, noise)
        mean, log_std = self.net(f).chunk(2, dim=-1)  # (B, M, 3) each
        log_std = self.LOG_STD_MIN + 0.5 * (self.LOG_STD_MAX - self.LOG_STD_MIN) * (torch.tanh(log_std) + 1)
        z = torch.zeros_like(mean) if deterministic else noise[:, :, 0]  # (B, M, 3)
        u = mean + log_std.exp() * z
        log_prob = -0.5 * z.pow(2).sum(-1) - log_std.sum(-1) - 0.5 * MOTION_DIM * LOG_2PI
        return torch.tanh(u), log_prob - tanh_log_det(u)


class Denoiser(nn.Module):
    """Per-point denoiser ``F_θ(x, t, f)``: ``[f, x, emb(t)] → H → H → out``, ReLU, shared by DDPM and CM.

    ``f`` is the same at every step of a chain, so its share of the first layer (``W_f f``) is
    computed once per chain (``in_f``); a step only adds ``W_x x`` and a per-time bias ``W_t emb(t)``.
    """

    def __init__(self, feature_dim: int, hidden: int, out_dim: int, time_dim: int = 16) -> None:
        super().__init__()
        self.in_f = nn.Linear(feature_dim, hidden)
        self.in_x = nn.Linear(MOTION_DIM, hidden, bias=False)
        self.in_t = nn.Linear(time_dim, hidden, bias=False)
        self.hidden = nn.Linear(hidden, hidden)
        self.out = nn.Linear(hidden, out_dim)
        self.register_buffer("freqs", torch.exp(torch.linspace(0.0, math.log(100.0), time_dim // 2)))

    def time_bias(self, t: torch.Tensor) -> torch.Tensor:
        """Scalar time features ``t (L,)`` → first-layer bias per time ``(L, H)`` (sinusoidal embedding)."""
        arg = t[:, None] * self.freqs  # (L, time_dim/2)
        return self.in_t(torch.cat([arg.sin(), arg.cos()], dim=-1))

    def forward(self, f: torch.Tensor, x: torch.Tensor, t_bias: torch.Tensor) -> torch.Tensor:
        """One evaluation: ``f (R, D)``, ``x (R, 3)``, ``t_bias (H,)`` → ``(R, out_dim)`` (unfused reference)."""
        h = torch.relu(self.in_f(f) + self.in_x(x) + t_bias)
        return self.out(torch.relu(self.hidden(h)))


@dataclass(frozen=True)
class DDPMSchedule:
    """Variance-preserving noise schedule for few steps (Diffusion-QL's ``vp_beta_schedule``).

    ``ᾱ_K`` ≈ 0.006 at K = 5, so ``u^K ~ N(0, I)`` matches the end of the forward process.
    """

    n_steps: int = 5
    """K, denoising steps."""
    beta_min: float = 0.1
    """VP schedule's β_min (continuous-time rate)."""
    beta_max: float = 10.0
    """VP schedule's β_max (continuous-time rate)."""
    final_std: float = 0.05
    """Std of the last step u^1 → u^0 (its posterior variance is 0, which would leave no density)."""

    def betas(self) -> torch.Tensor:
        """``β_k`` for k = 1..K, float64 ``(K,)``."""
        k = torch.arange(1, self.n_steps + 1, dtype=torch.float64)
        t = self.n_steps
        alpha = torch.exp(-self.beta_min / t - 0.5 * (self.beta_max - self.beta_min) * (2 * k - 1) / t**2)
        return 1.0 - alpha


@dataclass(frozen=True)
class ConsistencySchedule:
    """Noise levels of the multistep consistency sampler (Song et al. 2023; Karras et al. 2022 spacing).

    ``K + 1`` levels ``τ_K = sigma_max > … > τ_1 > τ_0 = final_std`` with ρ-spacing. Step k maps the
    sample at level τ_k to a clean estimate and re-noises it to level τ_{k−1}; the last re-noise (to
    τ_0) is the explicit final Gaussian that gives the chain a density.
    """

    n_steps: int = 5
    """K, consistency-function evaluations."""
    sigma_max: float = 5.0
    """T, the first level: u^K ~ N(0, T²). Actions live in tanh's pre-image (|u| ≲ 3), not images'
    [-1, 1] at 80, so a smaller T spends the K = 5 steps where the data is."""
    sigma_min: float = 0.002
    """ε, the boundary time: f_θ(x, ε) = x."""
    final_std: float = 0.05
    """τ_0, std of the explicit final Gaussian after the last (deterministic) consistency step."""
    sigma_data: float = 0.5
    """σ_data of the c_skip / c_out / c_in parameterisation."""
    rho: float = 7.0
    """ρ of the level spacing."""

    def levels(self) -> torch.Tensor:
        """``(τ_K, …, τ_1, τ_0)`` float64 ``(K + 1,)``, descending."""
        r = torch.linspace(0.0, 1.0, self.n_steps + 1, dtype=torch.float64)
        hi, lo = self.sigma_max ** (1 / self.rho), self.final_std ** (1 / self.rho)
        return (hi + r * (lo - hi)) ** self.rho


class _ChainPolicy(MotionPolicy):
    """Shared plumbing of the K-step chains: noise layout, the unrolled loop, log-prob estimators.

    A step is ``u_next = mean_j(u, F_θ(x_j(u), t_j, f)) + σ_j z_j``. Subclasses give the input scale
    ``x_j = in_scale_j·u``, the mean and the forward kernel of the bound; the loop lives here so DDPM
    and consistency sampling share one code path. The loop is written for the 2-core CPU, where an
    update is bound as much by per-op overhead as by FLOPs: per-step constants are folded into the
    weights once per call (``_fold``) and every log-prob term is computed once, vectorised over the
    stacked chain, after the loop.
    """

    stochastic_eval = True

    def __init__(
        self,
        feature_dim: int,
        hidden: int,
        n_steps: int,
        entropy: str,
        std_min: float,
        std_max: float,
    ) -> None:
        super().__init__()
        if entropy not in CHAIN_ENTROPY:
            raise ValueError(f"`entropy` must be one of {list(CHAIN_ENTROPY)}. Got {entropy}.")
        if not 0 < std_min < std_max:
            raise ValueError(f"need 0 < std_min < std_max. Got {std_min}, {std_max}.")
        self.n_steps, self.entropy = n_steps, entropy
        self.n_noise = n_steps + 1  # u^K plus one draw per step
        self.log_std_min, self.log_std_max = math.log(std_min), math.log(std_max)
        out = MOTION_DIM * (2 if entropy == "learned_std" else 1)
        self.denoiser = Denoiser(feature_dim, hidden, out)

    # Set by subclasses, sampling order (j = 0 is the step from pure noise):
    prior_std: float = 1.0  # u^K ~ N(0, prior_std²)
    step_std: list[float]  # fixed std σ_j of step j
    q_mean_coef: list[float]  # forward kernel q(u^k | u^{k−1}) = N(c_j·u^{k−1}, s_j²) …
    q_std: list[float]  # … of the bound

    def _time_features(self) -> torch.Tensor:
        """Scalar time feature of each step, ``(K,)``."""
        raise NotImplementedError

    def _fold(self, z: torch.Tensor) -> tuple[torch.Tensor, list[torch.Tensor], list]:
        """Per call: (``W_x^T`` per step ``(K, 3, H)``, ``σ_j z_j`` (+ folded biases) per step
        ``(R, 3)``, per-step output weights for ``_advance``)."""
        raise NotImplementedError

    def _advance(
        self, j: int, u: torch.Tensor, h: torch.Tensor, out_w, noise_j: torch.Tensor
    ) -> torch.Tensor:
        """Fixed-std step j: ``u (R, 3)``, last hidden ``h (R, H)`` → ``u_next (R, 3)``."""
        raise NotImplementedError

    def _mean(self, j: int, u: torch.Tensor, pred: torch.Tensor) -> torch.Tensor:
        """Mean of step j from the denoiser's prediction ``pred (R, 3)`` (learned-std path)."""
        raise NotImplementedError

    def sample(self, f, noise, deterministic=False):
        b, m = self._check(f, noise)
        if deterministic:
            noise = torch.zeros_like(noise)
        rows = b * m
        d = self.denoiser
        z = noise.reshape(rows, self.n_noise, MOTION_DIM)  # (R, K+1, 3) standard-normal draws
        cond = d.in_f(f.reshape(rows, -1))  # (R, H): W_f f + b, once per chain
        w_x, noise_terms, out_w = self._fold(z)
        # [u, 1] @ [W_x^T; W_t emb(t_j)]: the time bias rides in the same matmul as the input.
        t_bias = d.time_bias(self._time_features())  # (K, H)
        w_in = torch.cat([w_x, t_bias.unsqueeze(1)], dim=1).unbind(0)  # K × (4, H)
        ones = z.new_ones(rows, 1)
        learned = self.entropy == "learned_std"
        u = z[:, 0] * self.prior_std  # (R, 3): u^K
        states = [u]
        log_std_sum = 0.0  # Σ_k Σ_d log σ_k,d: a float for fixed stds, (R,) for learned ones
        for j in range(self.n_steps):  # unrolled: K dense steps
            h = torch.addmm(cond, torch.cat([u, ones], dim=1), w_in[j]).relu_()  # (R, H)
            h = F.linear(h, d.hidden.weight, d.hidden.bias).relu_()  # (R, H)
            if learned:
                pred, raw_std = F.linear(h, d.out.weight, d.out.bias).split(MOTION_DIM, dim=-1)
                log_std = self.log_std_min + (self.log_std_max - self.log_std_min) * torch.sigmoid(raw_std)
                u = torch.addcmul(self._mean(j, u, pred), log_std.exp(), z[:, j + 1])  # (R, 3)
                log_std_sum = log_std_sum + log_std.sum(-1)
            else:
                u = self._advance(j, u, h, out_w[j], noise_terms[j])  # (R, 3)
                log_std_sum += MOTION_DIM * math.log(self.step_std[j])
            states.append(u)
        # log p(u^K) + Σ_k log p_θ(u^{k−1} | u^k) of the reparameterised chain, from its draws.
        log_p = -0.5 * z.pow(2).sum((-1, -2)) - log_std_sum  # (R,)
        log_p = log_p - MOTION_DIM * (math.log(self.prior_std) + 0.5 * self.n_noise * LOG_2PI)
        if self.entropy == "bound":  # − Σ_k log q(u^k | u^{k−1}): the θ-dependent part of the bound
            chain = torch.stack(states, dim=0)  # (K+1, R, 3), sampling order u^K … u^0
            zq = (chain[:-1] - self.q_mean_coef_t * chain[1:]) * self.q_inv_std_t  # (K, R, 3)
            log_q = -0.5 * zq.pow(2).sum((0, -1))  # (R,) without constants
            log_q_const = -MOTION_DIM * (sum(map(math.log, self.q_std)) + 0.5 * self.n_steps * LOG_2PI)
            log_p = log_p - log_q - log_q_const
        log_p = log_p - tanh_log_det(u)  # change of variables motion = tanh(u^0)
        return torch.tanh(u).reshape(b, m, MOTION_DIM), log_p.reshape(b, m)

    def _register_kernel(self) -> None:
        """Buffers of the forward kernel, shaped to broadcast over the stacked chain ``(K, R, 3)``."""
        self.register_buffer("q_mean_coef_t", torch.tensor(self.q_mean_coef)[:, None, None])
        self.register_buffer("q_inv_std_t", 1.0 / torch.tensor(self.q_std)[:, None, None])
        self.register_buffer("step_std_t", torch.tensor(self.step_std)[None, :, None])  # (1, K, 1)


class DDPMPolicy(_ChainPolicy):
    """DDPM with K steps (Ho et al. 2020) as a per-point policy, sampled with explicit noise.

    The denoiser predicts the clean sample ``û^0 = F_θ(u^k, k, f)`` (Diffusion-QL's default for RL;
    an ε-predictor at initialisation outputs ≈ 0, so ``û^0 = u^k/√ᾱ_k`` and the first chains would
    saturate tanh at the corners of the cube). ``û^0`` is soft-clipped to ±3 (tanh(3) ≈ 0.995).
    Step ``p_θ(u^{k−1} | u^k) = N(μ̃_k(û^0, u^k), σ_k²)`` with the DDPM posterior mean μ̃ and
    ``σ_k² = β̃_k`` (posterior variance) for k ≥ 2, ``σ_1 = final_std``; ``u^K ~ N(0, I)``.
    Forward kernel of the bound: ``q(u^k | u^{k−1}) = N(√(1−β_k) u^{k−1}, β_k)``.
    """

    kind = "ddpm"
    X0_CLIP = 3.0

    def __init__(
        self,
        feature_dim: int,
        hidden: int = 64,
        schedule: DDPMSchedule | None = None,
        entropy: str = "bound",
        std_min: float = 0.01,
        std_max: float = 1.0,
    ) -> None:
        self.schedule = schedule or DDPMSchedule()
        super().__init__(feature_dim, hidden, self.schedule.n_steps, entropy, std_min, std_max)
        betas = self.schedule.betas()  # float64, index k − 1 for k = 1..K
        alphas = 1.0 - betas
        abar = torch.cumprod(alphas, 0)
        abar_prev = torch.cat([torch.ones(1, dtype=abar.dtype), abar[:-1]])
        post_std = (betas * (1 - abar_prev) / (1 - abar)).sqrt()
        post_std[0] = self.schedule.final_std  # β̃_1 = 0: the last step gets the explicit final std
        self.register_buffer("betas", betas.float())
        self.register_buffer("alphas_cumprod", abar.float())
        # Python floats in sampling order (j = 0 ↔ k = K): constants of the unrolled graph.
        rev = list(range(self.n_steps - 1, -1, -1))
        coef_x0 = abar_prev.sqrt() * betas / (1 - abar)  # posterior-mean weight on û^0
        coef_xt = alphas.sqrt() * (1 - abar_prev) / (1 - abar)  # posterior-mean weight on u^k
        self.coef_x0 = [float(coef_x0[i]) for i in rev]
        self.coef_xt = [float(coef_xt[i]) for i in rev]
        self.step_std = [float(post_std[i]) for i in rev]
        self.q_mean_coef = [float(alphas[i].sqrt()) for i in rev]
        self.q_std = [float(betas[i].sqrt()) for i in rev]
        self.register_buffer("step_time", torch.tensor([(i + 1) / self.n_steps for i in rev]))
        self._register_kernel()

    def _time_features(self):
        return self.step_time

    def _fold(self, z):
        w_x = self.denoiser.in_x.weight.t().expand(self.n_steps, -1, -1)  # (K, 3, H): u^k unscaled
        noise_terms = (z[:, 1:] * self.step_std_t).unbind(1)  # K × (R, 3): σ_j z_j
        # û^0 = c·tanh((W_o h + b)/c): fold 1/c into the output layer once per call.
        out = self.denoiser.out
        scaled = (out.weight * (1.0 / self.X0_CLIP), out.bias * (1.0 / self.X0_CLIP))
        return w_x, noise_terms, [scaled] * self.n_steps

    def _advance(self, j, u, h, out_w, noise_j):
        x0_scaled = torch.tanh(F.linear(h, *out_w))  # (R, 3) = û^0 / c
        mean = torch.add(u * self.coef_xt[j], x0_scaled, alpha=self.coef_x0[j] * self.X0_CLIP)
        return mean + noise_j

    def _mean(self, j, u, pred):
        x0 = torch.tanh(pred * (1.0 / self.X0_CLIP)) * self.X0_CLIP
        return torch.add(u * self.coef_xt[j], x0, alpha=self.coef_x0[j])


class ConsistencyPolicy(_ChainPolicy):
    """Multistep consistency model (Song et al. 2023; Consistency-AC, Ding & Jin 2023) as a policy.

    ``f_θ(x, t) = c_skip(t)·x + c_out(t)·F_θ(c_in(t)·x, t, f)`` with
    ``c_skip(t) = σ_d² / ((t − ε)² + σ_d²)``, ``c_out(t) = σ_d (t − ε) / √(σ_d² + t²)``, so
    ``c_skip(ε) = 1`` and ``c_out(ε) = 0`` exactly (boundary condition ``f_θ(x, ε) = x``).
    Sampling: ``u_K = T·z``; for k = K..1: ``u_{k−1} = f_θ(u_k, τ_k) + √(τ_{k−1}² − ε²)·z_k``; the last
    re-noise (to τ_0 = final_std) is the explicit final Gaussian, so every step has a density.
    Forward kernel of the bound (variance exploding): ``q(u_k | u_{k−1}) = N(u_{k−1}, τ_k² − τ_{k−1}²)``.
    """

    kind = "cm"

    def __init__(
        self,
        feature_dim: int,
        hidden: int = 64,
        schedule: ConsistencySchedule | None = None,
        entropy: str = "bound",
        std_min: float = 0.01,
        std_max: float = 1.0,
    ) -> None:
        self.schedule = schedule or ConsistencySchedule()
        s = self.schedule
        if not s.sigma_min < s.final_std < s.sigma_max:
            raise ValueError(
                f"need sigma_min < final_std < sigma_max. Got {s.sigma_min}, {s.final_std}, {s.sigma_max}."
            )
        super().__init__(feature_dim, hidden, s.n_steps, entropy, std_min, std_max)
        levels = s.levels()  # (K + 1,) float64, τ_K … τ_0
        self.register_buffer("levels", levels.float())
        self.prior_std = float(s.sigma_max)
        tau = levels[:-1]  # input level of each step, sampling order
        c_skip, c_out, c_in = self.coefficients(tau)
        self.c_skip, self.c_out = c_skip.tolist(), c_out.tolist()
        self.step_std = (levels[1:] ** 2 - s.sigma_min**2).sqrt().tolist()
        self.q_mean_coef = [1.0] * s.n_steps
        self.q_std = (levels[:-1] ** 2 - levels[1:] ** 2).sqrt().tolist()
        self.register_buffer("time_feature", (0.25 * torch.log(tau)).float())  # EDM's c_noise(τ)
        self.register_buffer("c_in_t", c_in.float()[:, None, None])  # (K, 1, 1)
        self.register_buffer("c_out_t", c_out.float()[:, None, None])  # (K, 1, 1)
        self._register_kernel()

    def coefficients(self, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(c_skip, c_out, c_in)`` at noise levels ``t`` (any shape)."""
        eps, sd = self.schedule.sigma_min, self.schedule.sigma_data
        c_skip = sd**2 / ((t - eps) ** 2 + sd**2)
        c_out = sd * (t - eps) / torch.sqrt(sd**2 + t**2)
        c_in = 1.0 / torch.sqrt(t**2 + sd**2)
        return c_skip, c_out, c_in

    def consistency_fn(self, f: torch.Tensor, x: torch.Tensor, t: float | torch.Tensor) -> torch.Tensor:
        """``f_θ(x, t)``: ``f (R, D)``, ``x (R, 3)`` at noise level ``t`` (scalar) → ``(R, 3)``.

        The same function the sampler evaluates (prediction head only; a learned-std head is dropped).
        """
        t = torch.as_tensor(t, dtype=x.dtype, device=x.device).reshape(1)
        c_skip, c_out, c_in = self.coefficients(t)
        t_bias = self.denoiser.time_bias(0.25 * torch.log(t))[0]
        return c_skip * x + c_out * self.denoiser(f, c_in * x, t_bias)[..., :MOTION_DIM]

    def _time_features(self):
        return self.time_feature

    def _fold(self, z):
        # F_θ(c_in·u): fold c_in into W_x;  c_skip·u + c_out·(W_o h + b) + σ z: fold c_out into W_o and
        # c_out·b + σ z into one additive term per step.
        # (Output weights stay (3, H) and enter matmuls transposed: with only 3 output columns the
        # transposed layout is ~2× faster on CPU than a contiguous (H, 3) matrix.)
        out = self.denoiser.out
        w_x = self.c_in_t * self.denoiser.in_x.weight.t()  # (K, 3, H): input c_in·u
        w_out = (self.c_out_t * out.weight[:MOTION_DIM]).unbind(0)  # K × (3, H)
        bias = self.c_out_t.squeeze(-1) * out.bias[:MOTION_DIM]  # (K, 3)
        noise_terms = (z[:, 1:] * self.step_std_t + bias).unbind(1)  # K × (R, 3)
        return w_x, noise_terms, w_out

    def _advance(self, j, u, h, out_w, noise_j):
        return torch.addmm(u, h, out_w.t(), beta=self.c_skip[j]) + noise_j  # f_θ(u, τ_j) + σ_j z_j

    def _mean(self, j, u, pred):
        return torch.add(u * self.c_skip[j], pred, alpha=self.c_out[j])


MOTION_POLICIES = ("tanh", "gauss", "ddpm", "cm")


def default_target_entropy(
    kind: str, entropy: str = "bound", ddpm: DDPMSchedule | None = None, cm: ConsistencySchedule | None = None
) -> float:
    """Default SAC target for the motion log-prob *estimate* of policy ``kind`` (nats).

    * gauss: ``−dim = −3`` (SAC's heuristic).
    * chains, ``"bound"``: the bound sits below the true entropy by the KL between the policy's chain
      and the forward kernel q. It is nearly tight for a chain as narrow as ``final_std`` and loose
      (several nats) for a wide one, whose last step (std ``final_std``) is much narrower than q's
      (``s_1``). The default ``−dim·(1 + ½·log(s_1 / final_std))`` sits between the two; measured on
      the bandit test, chains at this target sample ~0.05–0.1 per axis like a Gaussian policy at
      −dim, while a target of −dim kept them ~0.3 wide.
    * chains, ``"learned_std"``: ``−dim·K``, one Gaussian-policy target per step of the path density.
    * tanh: 0 (TD3 has no entropy term).
    """
    d = MOTION_DIM
    if kind == "gauss":
        return -float(d)
    if kind == "tanh":
        return 0.0
    sched = (ddpm or DDPMSchedule()) if kind == "ddpm" else (cm or ConsistencySchedule())
    if entropy == "learned_std":
        return -float(d * sched.n_steps)
    if kind == "ddpm":
        s_1 = float(sched.betas()[0].sqrt())
    else:
        levels = sched.levels()
        s_1 = float((levels[-2] ** 2 - levels[-1] ** 2).sqrt())
    return -d * (1.0 + 0.5 * math.log(s_1 / sched.final_std))


def make_motion_policy(
    kind: str,
    feature_dim: int,
    hidden: int,
    n_steps: int = 5,
    entropy: str = "bound",
    final_std: float = 0.05,
    std_min: float = 0.01,
    std_max: float = 1.0,
    ddpm: DDPMSchedule | None = None,
    cm: ConsistencySchedule | None = None,
) -> MotionPolicy:
    """Build the motion policy named ``kind`` (one of ``MOTION_POLICIES``)."""
    if kind == "tanh":
        return TanhPolicy(feature_dim, hidden)
    if kind == "gauss":
        return GaussPolicy(feature_dim, hidden)
    if kind == "ddpm":
        sched = ddpm or DDPMSchedule(n_steps=n_steps, final_std=final_std)
        return DDPMPolicy(feature_dim, hidden, sched, entropy, std_min, std_max)
    if kind == "cm":
        sched = cm or ConsistencySchedule(n_steps=n_steps, final_std=final_std)
        return ConsistencyPolicy(feature_dim, hidden, sched, entropy, std_min, std_max)
    raise ValueError(f"`motion` must be one of {list(MOTION_POLICIES)}. Got {kind}.")
