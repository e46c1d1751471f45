"""Policy loading, one home for every command: an eval TARGET (built-in baseline, training run,
checkpoint or exported model folder) → a batched policy (``hydo_cli.rollout.Policy``).

torch is imported only for runs and checkpoints: an exported model runs through onnxruntime alone.
The feasibility mask is made here, where each batch of observations arrives
(``sim.primitive.feasibility_mask``), and handed to the agent or the ONNX runner.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from hydo_cli.config import CHECKPOINT_FORMAT, TrainConfig
from hydo_cli.errors import HydoError
from hydo_cli.rollout import Policy, baseline_policy
from robot.onnx_interface import manifest_contacts
from sim.primitive import feasibility_mask

if TYPE_CHECKING:  # torch is imported only where a run or checkpoint is loaded
    import torch

    from models.algos import HybridAgent

BASELINES = ("heuristic", "random")


@dataclass
class LoadedPolicy:
    policy: Policy
    n_obj: int | None  # point counts the policy expects (None: any)
    n_bg: int | None
    stochastic: bool  # whether the policy samples at evaluation time
    description: str
    method: str = ""  # what --compare groups by: the run's / manifest's algo, or the baseline's name
    goals: str | None = None  # the goal mode it was trained on ("planar" | "6d"); None: a baseline
    contacts: str | None = None  # the contact model it was trained in (a run's config); None: unknown
    training: dict | None = None  # a run's training budget (``training_budget``); None: not a run


def load_policy(
    target: str,
    seed: int = 0,
    feasible_only: bool = True,
    weights: str | None = None,
    chain_noise: str | None = None,
) -> LoadedPolicy:
    """A baseline name, a run directory (its latest checkpoint) or a checkpoint file.

    ``feasible_only``: learned policies choose among points whose push can run
    (``sim.primitive.feasible_points``). ``weights``: "average" | "online" overrides a run's or
    checkpoint's ``AgentConfig.eval_weights``, ``chain_noise``: "sample" | "zero" its
    ``eval_chain_noise`` (None keeps them; baselines and exported models ignore both)."""
    if target in BASELINES:
        return LoadedPolicy(
            baseline_policy(target, seed, feasible_only), None, None, target == "random", target, target
        )
    path = Path(target)
    if not path.exists():
        raise HydoError(
            f"eval target '{target}' is neither a baseline ({', '.join(BASELINES)}) nor an existing run, "
            "checkpoint or model folder"
        )
    if path.is_dir() and (path / "manifest.json").exists():
        return load_onnx_policy(path, seed, feasible_only)
    if path.is_dir() and not (path / "checkpoint.pt").exists():
        what = (
            "has .onnx files but no manifest.json: re-export it"
            if any(path.glob("*.onnx"))
            else "holds neither checkpoint.pt (a training run) nor manifest.json (an exported model)"
        )
        raise HydoError(f"eval target '{target}' {what}")
    if path.is_file() and path.suffix == ".onnx":
        raise HydoError(f"eval target '{target}' is one graph of a model: give its folder ({path.parent})")
    return load_policy_from_checkpoint(path, seed, feasible_only, weights, chain_noise)


def load_onnx_policy(folder: Path, seed: int, feasible_only: bool = True) -> LoadedPolicy:
    """An exported model folder, run through onnxruntime (``robot.onnx_policy``, no torch)."""
    from robot.onnx_policy import OnnxPolicy

    model = OnnxPolicy.load(folder)
    rng = np.random.default_rng(seed)

    def policy(observations):
        points = np.stack([o["points"] for o in observations])
        features = np.stack([o["features"] for o in observations])
        normals = np.stack([o["normals"] for o in observations])
        noise = model.noise(len(observations), rng)
        feasible = feasibility_mask(points, normals) if feasible_only else None
        out = model.decide(points, features, noise, normals, feasible)
        return list(zip(out["index"].tolist(), out["motion"], strict=True))

    return LoadedPolicy(
        policy,
        model.n_obj,
        model.n_bg,
        model.stochastic,
        f"{model.manifest['algo']} (onnx {folder})",
        str(model.manifest["algo"]),
        str(model.manifest["goals"]),
        manifest_contacts(model.manifest),
    )


def stack_obs(observations: list[dict[str, np.ndarray]]) -> tuple[torch.Tensor, torch.Tensor]:
    """List of env observations → ``points (B, N, 3)``, ``features (B, N, 4)`` float32 tensors."""
    import torch

    points = torch.from_numpy(np.stack([o["points"] for o in observations]))
    features = torch.from_numpy(np.stack([o["features"] for o in observations]))
    return points, features


def agent_policy(agent: HybridAgent, mode: str, generator: torch.Generator, feasible_only: bool = True):
    """Wrap ``agent.act`` as a batched ``hydo_cli.rollout`` policy (``feasible_only``: choose among
    points whose push can run, see ``HybridAgent.act``)."""
    import torch

    def policy(observations):
        points, features = stack_obs(observations)
        normals = np.stack([o["normals"] for o in observations])
        # the mask is made here, where the observation is: the agent only applies it
        feasible = feasibility_mask(points.numpy(), normals) if feasible_only else None
        with torch.no_grad():
            index, motion, _ = agent.act(
                points,
                features,
                mode=mode,
                generator=generator,
                normals=torch.from_numpy(normals),
                feasible=feasible,
            )
        return list(zip(index.tolist(), motion.numpy(), strict=True))

    return policy


def training_budget(ckpt: dict, cfg: TrainConfig, agent: HybridAgent) -> dict | None:
    """What a run was given and what it had done at its checkpoint: a Table I "at the same budget"
    compares these, and one method's runs should share the ``learner`` settings. Recorded in each
    eval report's run (``training``). None for a checkpoint without counters."""
    if "counters" not in ckpt or "wall_s" not in ckpt:
        return None
    env_steps, updates, _ = (int(v) for v in ckpt["counters"])
    return {
        "env_steps": env_steps,
        "updates": updates,
        "sample_gradients": updates * cfg.batch_size,  # summed over the workers' shares of the batch
        "minutes": float(ckpt["wall_s"]) / 60,
        "max_minutes": cfg.max_minutes,  # 0: no wall-clock limit
        "workers": int(ckpt.get("workers", 1)),
        "objects": cfg.objects,
        "learner": {
            "batch_size": cfg.batch_size,
            "updates_per_step": cfg.updates_per_step,
            "denoise_steps": agent.config.denoise_steps,
            "policy_delay": agent.config.resolved_policy_delay,
        },
    }


def load_agent(path: Path) -> tuple[HybridAgent, TrainConfig, str]:
    """A run directory (its ``checkpoint.pt``) or a checkpoint file → ``(agent, config, command)``."""
    agent, cfg, command, _ = load_trained(path)
    return agent, cfg, command


def load_trained(path: Path) -> tuple[HybridAgent, TrainConfig, str, dict | None]:
    """``load_agent`` and the run's ``training_budget``."""
    path = Path(path)
    from models.algos import AgentConfig, HybridAgent
    from models.checkpoint import CheckpointError, load_checkpoint

    ckpt_path = path / "checkpoint.pt" if path.is_dir() else path
    if path.is_dir() and not ckpt_path.exists():
        raise HydoError(f"{path} is a folder without checkpoint.pt (not a training run)")
    ckpt = load_checkpoint(ckpt_path)
    if int(ckpt.get("format", -1)) != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{ckpt_path}: checkpoint format {ckpt.get('format')} != {CHECKPOINT_FORMAT}")
    try:
        cfg = TrainConfig.from_dict(json.loads(ckpt["config"]), str(ckpt_path))
        # The agent state records its full AgentConfig: a checkpoint made under older defaults
        # (before normals and 16 critic motion directions, say) loads with its own settings.
        agent = HybridAgent(AgentConfig.from_dict(ckpt["agent"]["config"]))
        agent.load_state_dict(ckpt["agent"])
    except (KeyError, TypeError, ValueError, RuntimeError, HydoError) as e:
        raise CheckpointError(
            f"{ckpt_path} does not hold a loadable hydo agent ({str(e).splitlines()[0][:120]})"
        ) from None
    command_file = ckpt_path.parent / "command.txt"
    command = command_file.read_text().strip() if command_file.exists() else "unknown"
    return agent, cfg, command, training_budget(ckpt, cfg, agent)


def load_policy_from_checkpoint(
    path: Path,
    seed: int,
    feasible_only: bool = True,
    weights: str | None = None,
    chain_noise: str | None = None,
) -> LoadedPolicy:
    """A run directory or checkpoint file → eval-mode batched policy (``weights`` overrides the
    agent's ``eval_weights``: "average" | "online"; ``chain_noise`` its ``eval_chain_noise``: "sample" |
    "zero")."""
    import torch

    agent, cfg, _, budget = load_trained(path)
    if weights is not None:
        agent.config = dataclasses.replace(agent.config, eval_weights=weights)
    if chain_noise is not None:
        agent.config = dataclasses.replace(agent.config, eval_chain_noise=chain_noise)
    policy = agent_policy(agent, "eval", torch.Generator().manual_seed(seed), feasible_only)
    return LoadedPolicy(
        policy,
        cfg.n_obj,
        cfg.n_bg,
        agent.eval_stochastic,
        f"{cfg.algo} ({path})",
        cfg.algo,
        cfg.goals,
        cfg.contacts,
        budget,
    )
