"""``hydo export``: a run's encoder, actor and critic as verified ONNX (``hydo_cli.onnx_export``)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from hydo_cli.errors import HydoError
from hydo_cli.onnx_export import export_agent
from hydo_cli.paths import check_writable_folder
from hydo_cli.policies import load_agent

HELP = """Export a trained run or checkpoint as ONNX (encoder.onnx, actor.onnx, critic.onnx, manifest.json),
verified against torch before it is written.

Examples:

  hydo export runs/hydo-cm-planar --out models/hydo-cm-planar

  hydo export runs/hacman-planar/checkpoint.pt --out models/hacman-planar
"""

console = Console(stderr=True)


def export(
    target: Annotated[Path, typer.Argument(help="Run directory or checkpoint file.")],
    out: Annotated[Path, typer.Option("--out", help="Output folder for the ONNX files and manifest.")],
    seed: Annotated[int, typer.Option("--seed", help="Seed of the verification observations.")] = 0,
    force: Annotated[
        bool, typer.Option("--force", help="Replace an existing model folder at --out.")
    ] = False,
) -> None:
    if out.exists() and not out.is_dir():
        raise HydoError(f"--out {out} is a file, not a model folder")
    if out.is_dir() and any(out.iterdir()) and not force:
        raise HydoError(f"--out {out} already holds files; give another --out or --force to replace it")
    check_writable_folder("--out", out)  # before the slow load and export, not after
    agent, cfg, command = load_agent(target)
    report = export_agent(agent, cfg, command, out, seed=seed)
    console.print(
        f"exported {cfg.algo} to {out}: onnxruntime vs torch over {report['n']} observations, max abs error "
        f"motion {report['max_abs_error_motion']:.1e}, Q {report['max_abs_error_q']:.1e}, "
        f"selected point agreement {report['index_agreement']:.0%}"
    )
