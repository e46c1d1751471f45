"""The training configuration: one home for ``TrainConfig``, its presets and how they resolve.

Used by ``hydo train`` (and the training loop, ``hydo_cli.trainer``), ``hydo export`` and loading a
run's checkpoint (``hydo_cli.policies``); saved as a run's ``config.json``.

``TrainConfig`` is a typed schema (a strict pydantic dataclass, ``sim.schema.STRICT``): every key of a
``--config`` TOML and of a ``config.json`` is checked against its type and range, and the keys against
each other, on construction; the nested ``[agent]`` table against ``models.algos.AgentConfig``'s fields
(:func:`check_agent_table`). :meth:`TrainConfig.parse` turns any failure into one line naming the file
and the key.
"""

from __future__ import annotations

import dataclasses
import json
import tomllib
import typing
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, Field, ValidationError, create_model, model_validator
from pydantic.dataclasses import dataclass

from hydo_cli.errors import HydoError
from models.choices import ALGOS, Algo
from sim.contract import CONTACT_MODELS, GOAL_MODES
from sim.schema import STRICT, one_line

#: Format of a run's ``checkpoint.pt`` (written by the trainer, read by ``policies.load_agent``).
CHECKPOINT_FORMAT = 1
#: TrainConfig keys that measurements showed do not help (docs/experiments.md), with the value that
#: made them inert: a run that recorded them at that value loads as before.
REMOVED_KEYS: dict[str, Any] = {"augment": "none", "tilt_shaping": 0.0}
#: Values of keys a config.json written before the key existed had in effect.
LEGACY_VALUES: dict[str, Any] = {"workers": 1}
#: Run fields that ``agent_config`` gives the learner itself: an ``[agent]`` table that names one must
#: agree with the run (else the table's value would be silently overridden).
RUN_AGENT_FIELDS = ("algo", "n_obj", "n_bg", "seed", "denoise_steps")
CLUTTER = (0, 1, 2, 5)

__all__ = ["Algo", "TrainConfig", "PRESETS", "resolve_config", "agent_config", "check_agent_table"]


def _one_of(choices: tuple):
    def check(v):
        if v not in choices:
            raise ValueError(f"must be one of {list(choices)}, got {v!r}")
        return v

    return AfterValidator(check)


# Types with their ranges; strict: a TOML string or boolean is never a count.
Count = Annotated[int, Field(ge=1)]
NonNegInt = Annotated[int, Field(ge=0)]
NonNegFloat = Annotated[float, Field(ge=0)]
Fraction = Annotated[float, Field(ge=0, le=1)]
AlgoName = Literal[tuple(ALGOS)]  # type: ignore[valid-type]
GoalMode = Literal[tuple(GOAL_MODES)]  # type: ignore[valid-type]
ContactModel = Literal[tuple(CONTACT_MODELS)]  # type: ignore[valid-type]
Clutter = Annotated[int, _one_of(CLUTTER)]
NonEmptyStr = Annotated[str, Field(min_length=1)]


@dataclass(frozen=True, config=STRICT)
class TrainConfig:
    """Everything a training run depends on; saved as ``config.json`` in the run."""

    algo: AlgoName = "hydo-cm"
    """Learner: one of hacman, hacman-diff, hacman-cm, hydo-gauss, hydo, hydo-cm (design.md §1)."""
    goals: GoalMode = "planar"
    """Goal mode: planar (translation) or 6d (stable pose)."""
    objects: NonEmptyStr = "train"
    """Object set (split name, object name or mesh folder)."""
    clutter: Clutter = 0
    """Extra scene objects: 0, 1, 2 or 5."""
    task: NonEmptyStr | None = None
    """Behaviour-diversity task (sim/tasks.py: push-line | push-align, random starts) instead of objects/goals."""
    steps: Count = 30_000
    """Environment steps (primitives) to train for."""
    max_minutes: NonNegFloat = 0.0
    """Wall-clock budget in minutes (0: none): stop, evaluate and checkpoint once it is spent."""
    seed: NonNegInt = 0
    """Seed of envs, networks and sampling (numpy refuses negative seeds)."""
    n_obj: Count = 128
    """Object points per observation."""
    n_bg: Count = 128
    """Background points per observation."""
    n_envs: Count = 8
    """Envs stepped in lock-step in this process (one batched decision per step)."""
    batch_size: Count = 64
    """Transitions per gradient update."""
    updates_per_step: NonNegFloat = 0.5
    """Gradient updates per env step (update-to-data ratio)."""
    learning_starts: NonNegInt = 1_000
    """Env steps with uniformly random actions before learning starts (at most ``steps``)."""
    buffer_size: Count = 200_000
    """Replay capacity in transitions."""
    denoise_steps: Count = 5
    """K: denoising steps of the ddpm / cm motion policies."""
    eval_every: NonNegInt = 5_000
    """Env steps between evaluations (0: only at the end)."""
    eval_episodes: Count = 50
    """Held-out episodes per evaluation."""
    checkpoint_every: Count = 5_000
    """Env steps between checkpoints."""
    log_every: Count = 500
    """Env steps between metric lines."""
    relabel_future: Fraction = 0.0
    """Hindsight relabelling: the fraction of each sampled batch whose goal becomes the object pose
    after this or a later primitive of its episode (HER's "future" strategy, models.replay)."""
    flip_share: Fraction | None = None
    """6D goals: the share of training episodes whose goal is a flip (another face up, tilt ≥ 30°);
    None draws goals as evaluation does (about half are flips). Evaluations during training and
    ``hydo eval`` always draw as drawn."""
    contacts: ContactModel = "hydo"
    """The training scene's contact model: "hydo", the scene's own, or "hacman", the contact settings
    of HACMan's bin env (``sim.scene`` lists them). ``hydo eval`` plays in the one a run was trained
    in unless ``--contacts`` says otherwise."""
    n_step: Count = 1
    """Primitives per TD target: the critic learns from the return of up to ``n_step`` primitives of
    an episode and bootstraps after them (``models.replay.ReplayBuffer.n_step_chain``)."""
    workers: Count = 2
    """Data-parallel worker processes, one per core (hydo_cli.trainer): each steps n_envs / workers
    envs and computes the gradient of batch_size / workers transitions. 1: the serial loop."""
    threads: Count = 1
    """torch intra-op threads per worker (a second thread in one process gains ~1.26×, a second
    worker ~1.9×: bench/trainer.py)."""
    precision: Literal["auto", "fp32", "bf16"] = "auto"
    """Arithmetic of the gradient updates (``models.perf.resolve_precision``): "auto" is bf16 autocast
    on CPUs with native bf16 (AMX / AVX-512-bf16) and fp32 elsewhere. A speed setting: it may differ
    on resume."""
    agent: dict[str, Any] = dataclasses.field(default_factory=dict)
    """Extra learner options passed to ``models.AgentConfig`` (e.g. {"actor_hidden": 128}; see AgentConfig)."""

    @model_validator(mode="after")
    def _agree(self) -> TrainConfig:
        """The keys against each other (each message is reported after the file's name)."""
        for name in ("n_envs", "batch_size", "buffer_size"):
            if getattr(self, name) % self.workers:
                raise ValueError(
                    f"`{name}` ({getattr(self, name)}) must be a multiple of `workers` ({self.workers}): "
                    "each worker takes an equal share"
                )
        if self.learning_starts > self.steps:
            raise ValueError(
                f"`learning_starts` ({self.learning_starts}) must be at most `steps` ({self.steps}): "
                "the run would never learn"
            )
        if self.relabel_future and self.task is not None:
            raise ValueError(
                "`relabel_future` needs a goal fixed over the episode; the --task goals follow the object"
            )
        if self.flip_share is not None and (self.goals != "6d" or self.task is not None):
            raise ValueError('`flip_share` mixes 6D goals: it needs goals = "6d" and no task')
        if self.task is not None:  # --task (eval issue): its scene replaces objects, goals and clutter
            from sim.tasks import TASK_NAMES

            if self.task not in TASK_NAMES:
                raise ValueError(f"`task` must be one of {list(TASK_NAMES)}, got {self.task!r}")
        return self

    @classmethod
    def parse(cls, values: dict[str, Any], source: str) -> TrainConfig:
        """Validated ``values`` (a config file's keys over the defaults) → TrainConfig, or one
        ``HydoError`` line naming ``source``, the key, what was expected and what was found. The
        ``[agent]`` table is checked too (:func:`check_agent_table`)."""
        if not isinstance(values, dict):
            raise HydoError(f"{source}: not a run configuration (a mapping), got {type(values).__name__}")
        try:
            cfg = cls(**values)
        except ValidationError as e:
            raise HydoError(one_line(e, source)) from None
        check_agent_table(cfg, source)
        return cfg

    def replace(self, source: str, **changes: Any) -> TrainConfig:
        """``dataclasses.replace`` with the same one-line errors (``--resume``'s --steps, --workers...)."""
        try:
            return dataclasses.replace(self, **changes)
        except ValidationError as e:
            raise HydoError(one_line(e, source)) from None

    @classmethod
    def from_dict(cls, d: dict[str, Any], source: str = "config") -> TrainConfig:
        """A saved ``config.json`` → TrainConfig (keys of removed options at their inert value are
        dropped; any other unknown key is refused)."""
        if not isinstance(d, dict):
            raise HydoError(f"{source}: not a run configuration (a JSON object), got {type(d).__name__}")
        for key, inert in REMOVED_KEYS.items():
            if key in d and d[key] != inert:
                raise HydoError(f"{source}: `{key}` = {d[key]!r} was removed from hydo (docs/experiments.md)")
        kept = {k: v for k, v in d.items() if k not in REMOVED_KEYS}
        return cls.parse({**LEGACY_VALUES, **kept}, source)

    @classmethod
    def load(cls, path: Path) -> TrainConfig:
        """A run's ``config.json`` → TrainConfig, or one line naming the file and what is wrong."""
        try:
            d = json.loads(Path(path).read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
            raise HydoError(f"{path}: not a readable JSON run configuration ({type(e).__name__})") from None
        return cls.from_dict(d, str(path))


def _agent_schema():
    """A strict pydantic model of ``models.algos.AgentConfig``'s fields (its types from the dataclass
    itself, so the two cannot drift), plus what a run's record may hold beside them."""
    from models.algos import REMOVED_INERT, REMOVED_OPTIONS, AgentConfig

    hints = typing.get_type_hints(AgentConfig)
    fields: dict[str, Any] = {f.name: (hints[f.name], f.default) for f in dataclasses.fields(AgentConfig)}
    fields["resolved"] = (dict[str, Any] | None, None)  # AgentConfig.to_dict's record of defaults
    for name in (*REMOVED_OPTIONS, *REMOVED_INERT):  # AgentConfig.from_dict refuses a live value
        fields[name] = (Any, None)
    return create_model("agent", __config__=STRICT, **fields)


def check_agent_table(cfg: TrainConfig, source: str) -> None:
    """Refuse an ``[agent]`` table (``cfg.agent``) whose keys are not AgentConfig fields, whose values
    have the wrong type or range, or that names a run field with another value than the run's.
    Imports torch (``models.algos``) only when the table is not empty."""
    if not cfg.agent:
        return
    try:
        _agent_schema()(**cfg.agent)
    except ValidationError as e:
        raise HydoError(one_line(e, source, prefix="agent")) from None
    for name in RUN_AGENT_FIELDS:
        if name in cfg.agent and cfg.agent[name] != getattr(cfg, name):
            raise HydoError(
                f"{source}: `agent.{name}` = {cfg.agent[name]!r} disagrees with `{name}` = "
                f"{getattr(cfg, name)!r}: set it once, outside [agent]"
            )
    try:
        agent_config(cfg)  # AgentConfig's own range checks (``__post_init__``)
    except ValueError as e:  # its messages name the field as `name`: say which table it is in
        raise HydoError(f"{source}: {str(e).replace('`', '`agent.', 1)}") from None


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
            values.update(tomllib.loads(Path(config_file).read_text(encoding="utf-8")))
        except FileNotFoundError:
            raise HydoError(f"config file {config_file} does not exist") from None
        except (OSError, UnicodeDecodeError) as e:
            raise HydoError(f"config file {config_file} cannot be read ({type(e).__name__})") from None
        except tomllib.TOMLDecodeError as e:
            raise HydoError(f"config file {config_file} is not valid TOML: {e}") from None
    flags = {k: v for k, v in overrides.items() if v is not None}
    values.update(flags)
    # A flag's bad value is the flag's fault, not the file's: name what the user wrote.
    source = str(config_file) if config_file is not None else "the configuration"
    try:
        TrainConfig(**values)
    except ValidationError as e:
        first = e.errors()[0]["loc"]
        if first and first[0] in flags:
            source = f"command line (--{FLAG_OF.get(first[0], first[0])})"
        elif config_file is None and preset is not None:
            source = f"--preset {preset}"
    return TrainConfig.parse(values, source)


#: The ``hydo train`` flag of each TrainConfig key it sets, where the names differ.
FLAG_OF = {"denoise_steps": "k", "max_minutes": "minutes"}


def agent_config(cfg: TrainConfig):
    """The learner's ``models.algos.AgentConfig`` of a run (imports torch)."""
    from models.algos import AgentConfig

    # ``cfg.agent`` holds the options a user set, or (in a run's config.json) the full resolved
    # AgentConfig; the run's own fields win where both name one.
    run = dict(algo=cfg.algo, n_obj=cfg.n_obj, n_bg=cfg.n_bg, seed=cfg.seed, denoise_steps=cfg.denoise_steps)
    return AgentConfig.from_dict({**cfg.agent, **run})
