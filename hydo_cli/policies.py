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
    method: str = ""  # what --compare groups by: the run's / manifest's algo, or the baseline's name


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
        return LoadedPolicy(baseline_policy(target, seed), None, None, target == "random", target, target)
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
    from hydo_cli.trainer import load_policy_from_checkpoint  # torch: only for runs and checkpoints

    return load_policy_from_checkpoint(path, seed, feasible_only, weights, chain_noise)


def load_onnx_policy(folder: Path, seed: int, feasible_only: bool = True) -> LoadedPolicy:
    """An exported model folder, run through onnxruntime (``robot.onnx_policy``, no torch)."""
    import numpy as np

    from robot.onnx_policy import OnnxPolicy

    model = OnnxPolicy.load(folder)
    rng = np.random.default_rng(seed)

    def policy(observations):
        points = np.stack([o["points"] for o in observations])
        features = np.stack([o["features"] for o in observations])
        normals = np.stack([o["normals"] for o in observations])
        noise = model.noise(len(observations), rng)
        out = model.decide(points, features, noise, normals, feasible_only=feasible_only)
        return list(zip(out["index"].tolist(), out["motion"], strict=True))

    return LoadedPolicy(
        policy,
        model.n_obj,
        model.n_bg,
        model.stochastic,
        f"{model.manifest['algo']} (onnx {folder})",
        str(model.manifest["algo"]),
    )
