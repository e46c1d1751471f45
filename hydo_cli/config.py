"""The training configuration: one home for ``TrainConfig``, its presets and how they resolve.

Used by ``hydo train`` (and the training loop, ``hydo_cli.trainer``), ``hydo export`` and loading a
run's checkpoint (``hydo_cli.policies``); saved as a run's ``config.json``.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hydo_cli.errors import HydoError
from models.choices import ALGOS, Algo
from sim.contract import GOAL_MODES

#: Format of a run's ``checkpoint.pt`` (written by the trainer, read by ``policies.load_agent``).
CHECKPOINT_FORMAT = 1
#: TrainConfig keys that measurements showed do not help (docs/experiments.md), with the value that
#: made them inert: a run that recorded them at that value loads as before.
REMOVED_KEYS: dict[str, Any] = {"augment": "none"}
#: Values of keys a config.json written before the key existed had in effect.
LEGACY_VALUES: dict[str, Any] = {"workers": 1}

__all__ = ["Algo", "TrainConfig", "PRESETS", "resolve_config", "agent_config"]


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
    relabel_future: float = 0.0
    """Hindsight relabelling: the fraction of each sampled batch whose goal becomes the object pose
    after this or a later primitive of its episode (HER's "future" strategy, models.replay)."""
    workers: int = 2
    """Data-parallel worker processes, one per core (hydo_cli.trainer): each steps n_envs / workers
    envs and computes the gradient of batch_size / workers transitions. 1: the serial loop."""
    threads: int = 1
    """torch intra-op threads per worker (a second thread in one process gains ~1.26×, a second
    worker ~1.9×: bench/trainer.py)."""
    agent: dict = dataclasses.field(default_factory=dict)
    """Extra learner options passed to ``models.AgentConfig`` (e.g. {"actor_hidden": 128}; see AgentConfig)."""

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "config") -> TrainConfig:
        """A saved ``config.json`` → TrainConfig (keys of removed options at their inert value are
        dropped; any other unknown key is refused)."""
        for key, inert in REMOVED_KEYS.items():
            if key in d and d[key] != inert:
                raise HydoError(f"{source}: `{key}` = {d[key]!r} was removed from hydo (docs/experiments.md)")
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known - set(REMOVED_KEYS))
        if unknown:
            raise HydoError(f"{source}: unknown config keys {unknown}")
        return cls(**{**LEGACY_VALUES, **{k: v for k, v in d.items() if k in known}})

    @classmethod
    def load(cls, path: Path) -> TrainConfig:
        """A run's ``config.json`` → TrainConfig, or one line naming the file and what is wrong."""
        try:
            d = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise HydoError(f"{path}: not a readable JSON run configuration ({type(e).__name__})") from None
        if not isinstance(d, dict):
            raise HydoError(f"{path}: not a run configuration (a JSON object), got {type(d).__name__}")
        for f in dataclasses.fields(cls):
            if f.name in d and not _has_type(d[f.name], f.type):
                raise HydoError(f"{path}: `{f.name}` must be {f.type}, got {d[f.name]!r}")
        try:
            return cls.from_dict(d, str(path))
        except HydoError as e:
            msg = str(e)
            raise HydoError(msg if msg.startswith(str(path)) else f"{path}: {msg}") from None

    def __post_init__(self):
        if self.algo not in ALGOS:
            raise HydoError(f"`algo` must be one of {list(ALGOS)}. Got {self.algo!r}.")
        if self.goals not in GOAL_MODES:
            raise HydoError(f"`goals` must be one of {list(GOAL_MODES)}. Got {self.goals!r}.")
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
            "workers",
        ):
            if getattr(self, name) < 1:
                raise HydoError(f"`{name}` must be at least 1. Got {getattr(self, name)}.")
        for name in ("n_envs", "batch_size", "buffer_size"):
            if getattr(self, name) % self.workers:
                raise HydoError(
                    f"`{name}` ({getattr(self, name)}) must be a multiple of `workers` ({self.workers}): "
                    "each worker takes an equal share"
                )
        if self.max_minutes < 0:
            raise HydoError(f"`max_minutes` (--minutes) must be >= 0 (0: no budget). Got {self.max_minutes}.")
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


def _has_type(value: Any, annotation: str) -> bool:
    """Whether a JSON value fits a TrainConfig field's annotation (``int``, ``float``, ``str | None``, ...)."""
    kinds = {
        "int": (int,),
        "float": (int, float),
        "str": (str,),
        "dict": (dict,),
        "bool": (bool,),
        "None": (),
    }
    options = [a.strip() for a in annotation.split("|")]
    if value is None:
        return "None" in options
    if isinstance(value, bool) and "bool" not in options:  # JSON true is not a step count
        return False
    return any(isinstance(value, kinds.get(a, (object,))) for a in options)


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


def agent_config(cfg: TrainConfig):
    """The learner's ``models.algos.AgentConfig`` of a run (imports torch)."""
    from models.algos import AgentConfig

    # ``cfg.agent`` holds the options a user set, or (in a run's config.json) the full resolved
    # AgentConfig; the run's own fields win where both name one.
    run = dict(algo=cfg.algo, n_obj=cfg.n_obj, n_bg=cfg.n_bg, seed=cfg.seed, denoise_steps=cfg.denoise_steps)
    return AgentConfig.from_dict({**cfg.agent, **run})
