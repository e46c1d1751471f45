"""``hydo train``: one process that interleaves env steps and gradient updates (the fastest layout on
2 cores: env worker processes next to a 2-thread learner cut its throughput by 65-73%).

Run directory (``--out``)::

    config.json      the resolved configuration (preset < --config TOML < command-line flags)
    command.txt      the command line; system.json: package versions and machine
    metrics.jsonl    one line per log interval: env steps, updates, wall time, losses, temperatures
    eval.jsonl       periodic evaluation on held-out episodes (success rate, return)
    checkpoint.pt    latest checkpoint (atomic), also written at the end and on Ctrl-C
    replay.npz       the replay buffer at the last checkpoint, so --resume continues exactly

``--resume`` continues the step counter, networks, optimisers, temperatures, RNG and replay buffer;
episodes in flight at the cut are restarted.
"""

from __future__ import annotations

import dataclasses
import json
import os
import platform
import shlex
import sys
import time
import tomllib
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

from hydo_cli.errors import HydoError
from hydo_cli.options import TaskOpt
from sim.atomic import atomic_write_text

HELP = """Train a hybrid policy (HyDo or a baseline) in the simulated bin.

Examples:

  hydo train --preset quick                      # the README's few-minute run

  hydo train --algo hydo-cm --goals planar --objects train --steps 40000 --out runs/hydo-cm-planar

  hydo train --resume runs/hydo-cm-planar        # continue a cut run
"""

console = Console(stderr=True)


class Algo(str, Enum):
    hacman = "hacman"
    hacman_diff = "hacman-diff"
    hacman_cm = "hacman-cm"
    hydo_gauss = "hydo-gauss"
    hydo = "hydo"
    hydo_cm = "hydo-cm"


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on; saved as ``config.json`` in the run."""

    algo: str = "hydo-cm"
    """Learner: one of hacman, hacman-diff, hacman-cm, hydo-gauss, hydo, hydo-cm (design.md §1)."""
    goals: str = "planar"
    """Goal mode: planar (translation) or 6d (stable pose)."""
    objects: str = "train"
    """Object set (split name, object name or mesh folder)."""
    clutter: int = 0
    """Extra scene objects: 0, 1, 2 or 5."""
    task: str | None = None
    """Behaviour-diversity task (sim/tasks.py: push-line | push-align, random starts) instead of objects/goals."""
    steps: int = 30_000
    """Environment steps (primitives) to train for."""
    max_minutes: float = 0.0
    """Wall-clock budget in minutes (0: none): stop, evaluate and checkpoint once it is spent."""
    seed: int = 0
    """Seed of envs, networks and sampling."""
    n_obj: int = 128
    """Object points per observation."""
    n_bg: int = 128
    """Background points per observation."""
    n_envs: int = 8
    """Envs stepped in lock-step in this process (one batched decision per step)."""
    batch_size: int = 64
    """Transitions per gradient update."""
    updates_per_step: float = 0.5
    """Gradient updates per env step (update-to-data ratio)."""
    learning_starts: int = 1_000
    """Env steps with uniformly random actions before learning starts."""
    buffer_size: int = 200_000
    """Replay capacity in transitions."""
    denoise_steps: int = 5
    """K: denoising steps of the ddpm / cm motion policies."""
    eval_every: int = 5_000
    """Env steps between evaluations (0: only at the end)."""
    eval_episodes: int = 50
    """Held-out episodes per evaluation."""
    checkpoint_every: int = 5_000
    """Env steps between checkpoints."""
    log_every: int = 500
    """Env steps between metric lines."""
    augment: str = "none"
    """Replay augmentation: none, or yaw90 (each sampled transition's scene turned about z by a random
    multiple of 90°; physics is invariant under rotations about gravity; see models.replay)."""
    relabel_future: float = 0.0
    """Hindsight relabelling: the fraction of each sampled batch whose goal becomes the object pose
    after this or a later primitive of its episode (HER's "future" strategy, models.replay)."""
    threads: int = 2
    """torch intra-op threads: 2 on an idle 2-core machine, 1 when two runs share it."""
    agent: dict = dataclasses.field(default_factory=dict)
    """Extra learner options passed to ``models.AgentConfig`` (e.g. {"actor_hidden": 128}; see AgentConfig)."""

    def __post_init__(self):
        algos = [a.value for a in Algo]
        if self.algo not in algos:
            raise HydoError(f"`algo` must be one of {algos}. Got {self.algo!r}.")
        if self.goals not in ("planar", "6d"):
            raise HydoError(f"`goals` must be one of ['planar', '6d']. Got {self.goals!r}.")
        if self.clutter not in (0, 1, 2, 5):
            raise HydoError(f"`clutter` must be one of [0, 1, 2, 5]. Got {self.clutter!r}.")
        for name in (
            "steps",
            "n_obj",
            "n_bg",
            "n_envs",
            "batch_size",
            "buffer_size",
            "denoise_steps",
            "threads",
        ):
            if getattr(self, name) < 1:
                raise HydoError(f"`{name}` must be at least 1. Got {getattr(self, name)}.")
        from models.replay import AUGMENTATIONS

        if self.augment not in AUGMENTATIONS:
            raise HydoError(f"`augment` must be one of {list(AUGMENTATIONS)}. Got {self.augment!r}.")
        if self.updates_per_step < 0:
            raise HydoError(f"`updates_per_step` must be >= 0. Got {self.updates_per_step}.")
        if not 0.0 <= self.relabel_future <= 1.0:
            raise HydoError(f"`relabel_future` must be in [0, 1]. Got {self.relabel_future}.")
        if self.relabel_future and self.task is not None:
            raise HydoError(
                "`relabel_future` needs a goal fixed over the episode; the --task goals follow the object"
            )
        if self.task is not None:  # --task (eval issue): its scene replaces objects, goals and clutter
            from sim.tasks import TASK_NAMES

            if self.task not in TASK_NAMES:
                raise HydoError(f"`task` must be one of {list(TASK_NAMES)}. Got {self.task!r}.")


#: Named starting points; flags and --config override them.
PRESETS: dict[str, dict[str, Any]] = {
    # The README's main job: a few minutes on 2 cores, planar pushes of the cube, visibly learning.
    "quick": dict(
        algo="hydo-cm",
        objects="cube",
        goals="planar",
        steps=4_000,
        learning_starts=500,
        eval_every=1_000,
        eval_episodes=20,
        checkpoint_every=1_000,
        log_every=200,
    ),
    "default": {},
}


def resolve_config(preset: str | None, config_file: Path | None, overrides: dict[str, Any]) -> TrainConfig:
    """defaults < preset < TOML file < explicit command-line flags (None means "not given")."""
    values: dict[str, Any] = {}
    if preset is not None:
        if preset not in PRESETS:
            raise HydoError(f"`--preset` must be one of {list(PRESETS)}. Got {preset!r}.")
        values.update(PRESETS[preset])
    if config_file is not None:
        try:
            values.update(tomllib.loads(Path(config_file).read_text()))
        except FileNotFoundError:
            raise HydoError(f"config file {config_file} does not exist") from None
        except tomllib.TOMLDecodeError as e:
            raise HydoError(f"config file {config_file} is not valid TOML: {e}") from None
    values.update({k: v for k, v in overrides.items() if v is not None})
    known = {f.name for f in dataclasses.fields(TrainConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise HydoError(f"unknown config keys {unknown}; known keys: {sorted(known)}")
    return TrainConfig(**values)


def system_info() -> dict[str, Any]:
    import importlib.metadata as md

    versions = {}
    for pkg in ("hydo", "torch", "mujoco", "numpy", "gymnasium", "onnx", "onnxruntime"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            versions[pkg] = None
    return {
        "python": sys.version,
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "versions": versions,
    }


def _default_out(cfg: TrainConfig) -> Path:
    return (
        Path("runs")
        / f"{cfg.algo}-{cfg.goals}-{cfg.objects.replace('/', '_')}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    )


def train(
    algo: Annotated[
        Algo | None, typer.Option("--algo", help="Learner (design.md §1). [default: hydo-cm]")
    ] = None,
    goals: Annotated[str | None, typer.Option("--goals", help="planar | 6d. [default: planar]")] = None,
    objects: Annotated[
        str | None, typer.Option("--objects", help="Object set, object name or mesh folder. [default: train]")
    ] = None,
    clutter: Annotated[
        int | None, typer.Option("--clutter", help="Extra scene objects: 0, 1, 2 or 5.")
    ] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Env steps (primitives) to train for.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed.")] = None,
    denoise_steps: Annotated[int | None, typer.Option("--k", help="Denoising steps K (ddpm / cm).")] = None,
    task: TaskOpt = None,
    max_minutes: Annotated[
        float | None, typer.Option("--minutes", help="Wall-clock budget (0: none).")
    ] = None,
    threads: Annotated[
        int | None,
        typer.Option("--threads", help="torch threads: 2 alone on 2 cores, 1 if two runs share them."),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Run directory (default: runs/<algo>-...).")
    ] = None,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="Continue the run in this directory.")
    ] = None,
    config: Annotated[Path | None, typer.Option("--config", help="TOML file of config keys.")] = None,
    preset: Annotated[str | None, typer.Option("--preset", help=f"One of {list(PRESETS)}.")] = None,
) -> None:
    if resume is not None:
        run_dir = Path(resume)
        if not (run_dir / "config.json").exists():
            raise HydoError(f"--resume {run_dir}: not a run directory (no config.json)")
        cfg = TrainConfig(**json.loads((run_dir / "config.json").read_text()))
        if steps is not None:  # allow extending a finished run
            cfg = dataclasses.replace(cfg, steps=steps)
        if threads is not None:  # a speed setting, not a learning one: may differ on resume
            cfg = dataclasses.replace(cfg, threads=threads)
    else:
        cfg = resolve_config(
            preset,
            config,
            dict(
                algo=algo.value if algo else None,
                goals=goals,
                objects=objects,
                clutter=clutter,
                steps=steps,
                seed=seed,
                denoise_steps=denoise_steps,
                max_minutes=max_minutes,
                threads=threads,
                task=task.value if task else None,
            ),
        )
        run_dir = out or _default_out(cfg)
        if (run_dir / "checkpoint.pt").exists():
            raise HydoError(f"{run_dir} already holds a run; use --resume {run_dir} or another --out")
    from hydo_cli.trainer import Trainer

    trainer = Trainer(cfg, run_dir, resume=resume is not None)
    if resume is None:
        run_dir.mkdir(parents=True, exist_ok=True)
        atomic_write_text(run_dir / "config.json", json.dumps(dataclasses.asdict(cfg), indent=2))
        atomic_write_text(run_dir / "command.txt", shlex.join(["hydo", *sys.argv[1:]]) + "\n")
        atomic_write_text(run_dir / "system.json", json.dumps({**system_info(), **trainer.cpu}, indent=2))
    trainer.run()
