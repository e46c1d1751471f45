"""``hydo export``: the encoder, actor and critic of a run as verified ONNX (issue: export)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from hydo_cli.errors import HydoError

HELP = """Export a trained run or checkpoint as ONNX (encoder.onnx, actor.onnx, critic.onnx, manifest.json).

Examples:

  hydo export runs/hydo-cm-planar --out models/hydo-cm-planar
"""


def export(
    target: Annotated[Path, typer.Argument(help="Run directory or checkpoint file.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder for the ONNX files and manifest.")] = Path(
        "models/policy"
    ),
) -> None:
    raise HydoError("`hydo export` is not implemented yet (open issue: ONNX export); nothing was written.")
