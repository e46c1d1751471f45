"""Every named choice of the learner, in one torch-free home shared by the CLI, configs and models.

The six algorithms are one table of choices (design.md §1), not a class tree: ``ALGOS`` maps each
``--algo`` to its row. The enums are ``str`` enums, so a config file, a checkpoint and a typer option
all hold the same plain strings.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum


@dataclass(frozen=True)
class AlgoSpec:
    """One row of the algorithm table."""

    paper_name: str
    objective: str  # "td3" | "sac"
    motion: str  # "tanh" | "gauss" | "ddpm" | "cm"
    entropy: str  # "none" | "location+motion" | "location+chain"


ALGOS: dict[str, AlgoSpec] = {
    "hacman": AlgoSpec("HACMan", "td3", "tanh", "none"),
    "hacman-diff": AlgoSpec("HACMan + Diff", "td3", "ddpm", "none"),
    "hacman-cm": AlgoSpec("HACMan + CM", "td3", "cm", "none"),
    "hydo-gauss": AlgoSpec("HyDo (w/o Diff)", "sac", "gauss", "location+motion"),
    "hydo": AlgoSpec("HyDo", "sac", "ddpm", "location+chain"),
    "hydo-cm": AlgoSpec("HyDo + CM", "sac", "cm", "location+chain"),
}

#: ``--algo``: the rows of ``ALGOS``.
Algo = Enum("Algo", {name.replace("-", "_"): name for name in ALGOS}, type=str)


class Mode(str, Enum):
    """How the agent acts: sampling to explore (training) or its evaluation policy."""

    explore = "explore"
    eval = "eval"


class EvalWeights(str, Enum):
    """Weights that act in evaluation, export and deploy: the Polyak-averaged target networks or the
    last gradient step's."""

    average = "average"
    online = "online"


class ChainNoise(str, Enum):
    """How a ddpm / cm chain acts in evaluation: on sampled noise (the paper) or on zero noise."""

    sample = "sample"
    zero = "zero"


MODES = tuple(m.value for m in Mode)
EVAL_WEIGHTS = tuple(w.value for w in EvalWeights)
EVAL_CHAIN_NOISE = tuple(c.value for c in ChainNoise)
