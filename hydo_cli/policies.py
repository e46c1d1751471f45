"""Turning an eval TARGET into a batched policy: built-in baselines, runs and checkpoints."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from hydo_cli.errors import HydoError
from hydo_cli.rollout import Policy, baseline_policy

BASELINES = ("heuristic", "random")


@dataclass
class LoadedPolicy:
    policy: Policy
    n_obj: int | None  # point counts the policy expects (None: any)
    n_bg: int | None
    stochastic: bool  # whether the policy samples at evaluation time
    description: str


def load_policy(target: str, seed: int = 0) -> LoadedPolicy:
    """A baseline name, a run directory (its latest checkpoint) or a checkpoint file."""
    if target in BASELINES:
        return LoadedPolicy(baseline_policy(target, seed), None, None, target == "random", target)
    path = Path(target)
    if not path.exists():
        raise HydoError(
            f"eval target '{target}' is neither a baseline ({', '.join(BASELINES)}) nor an existing run, "
            "checkpoint or model folder"
        )
    from hydo_cli.train import load_agent_policy

    return load_agent_policy(path, seed)
