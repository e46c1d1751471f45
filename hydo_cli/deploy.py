"""``hydo deploy``: run an exported ONNX policy on a Panda / FR3 or its MuJoCo twin (issue: deploy)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hydo_cli.errors import HydoError

app = typer.Typer(
    help="Run an exported ONNX policy on a Franka arm with depth cameras, or on its MuJoCo twin.",
    invoke_without_command=True,
)


@app.callback()
def deploy(
    ctx: typer.Context,
    robot: Annotated[str, typer.Option("--robot", help="panda | fr3 | sim (the MuJoCo twin).")] = "sim",
    model: Annotated[Path | None, typer.Option("--model", help="Exported model folder.")] = None,
) -> None:
    """Examples:

    hydo deploy --robot sim --model models/hydo-cm-planar

    hydo deploy --robot panda --model models/hydo-cm-6d --cell cell.yaml --goal goal.npz
    """
    if ctx.invoked_subcommand is None:
        raise HydoError(
            "`hydo deploy` is not implemented yet (open issue: deploy); no camera was opened and no robot moved."
        )
