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
    if path.is_dir() and (path / "manifest.json").exists():
        return load_onnx_policy(path, seed)
    from hydo_cli.train import load_agent_policy

    return load_agent_policy(path, seed)


def load_onnx_policy(folder: Path, seed: int) -> LoadedPolicy:
    """An exported model folder, run through onnxruntime (``robot.onnx_policy``, no torch)."""
    import numpy as np

    from robot.onnx_policy import OnnxPolicy

    model = OnnxPolicy.load(folder)
    rng = np.random.default_rng(seed)

    def policy(observations):
        points = np.stack([o["points"] for o in observations])
        features = np.stack([o["features"] for o in observations])
        out = model.decide(points, features, model.noise(len(observations), rng))
        return list(zip(out["index"].tolist(), out["motion"], strict=True))

    return LoadedPolicy(
        policy, model.n_obj, model.n_bg, model.stochastic, f"{model.manifest['algo']} (onnx {folder})"
    )
