"""Option types shared by several commands, so a flag has the same name, choices and help everywhere."""

from __future__ import annotations

from enum import Enum
from typing import Annotated

import typer


class Goals(str, Enum):
    planar = "planar"
    sixd = "6d"


class ObsSource(str, Enum):
    mesh = "mesh"
    render = "render"


class EvalWeights(str, Enum):
    """Weights a trained agent acts with in evaluation (``models.algos.EVAL_WEIGHTS``; a test keeps
    the two lists equal)."""

    average = "average"
    online = "online"


class ChainNoise(str, Enum):
    """How a trained chain policy samples in evaluation (``models.algos.EVAL_CHAIN_NOISE``; a test
    keeps the two lists equal)."""

    sample = "sample"
    zero = "zero"


class TaskName(str, Enum):
    """Behaviour-diversity tasks (``sim.tasks.TASKS``; a test keeps the two lists equal)."""

    push_line = "push-line"
    push_align = "push-align"


ObjectsOpt = Annotated[
    str,
    typer.Option(
        "--objects",
        help="Object set: train | unseen-instance | unseen-category | unseen | all | cube | an object name "
        "| a folder of .obj/.stl meshes.",
    ),
]
GoalsOpt = Annotated[Goals, typer.Option("--goals", help="Goal mode: planar (translation only) or 6d.")]
ClutterOpt = Annotated[
    int, typer.Option("--clutter", help="Extra scene objects in the background: 0, 1, 2 or 5.")
]
SeedOpt = Annotated[int, typer.Option("--seed", help="Random seed (episodes, goals, networks).")]
TaskOpt = Annotated[
    TaskName | None,
    typer.Option(
        "--task",
        help="Behaviour-diversity task (paper §V-C, sim/tasks.py): push-line (|B|=24) or push-align (|B|=2). "
        "It fixes the object (cube), start, goal and obstacles.",
    ),
]
