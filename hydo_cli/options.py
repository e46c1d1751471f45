"""Option types shared by several commands, so a flag has the same name, choices and help everywhere."""

from __future__ import annotations

from typing import Annotated

import typer

from models.choices import ChainNoise, EvalWeights
from sim.contract import Contacts, Goals, ObsSource
from sim.tasks import TaskName

__all__ = ["ChainNoise", "Contacts", "EvalWeights", "Goals", "ObsSource", "TaskName"]


ObjectsOpt = Annotated[
    str,
    typer.Option(
        "--objects",
        help="Object set: train | unseen-instance | unseen-category | unseen | all | cube | train-wide "
        "(train plus 64 more instances of its categories) | train-varied (train-wide plus 32 irregular "
        "polyhedra and stepped blocks) | an object name | a folder of .obj/.stl meshes.",
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
