"""``hydo plot``: learning curves of training runs as a picture (and, with ``--json``, the numbers)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from hydo_cli.errors import HydoError
from hydo_cli.figures import check_image_path, curves_data, curves_figure, load_run, save_figure
from hydo_cli.paths import check_writable
from sim.atomic import atomic_write_text

HELP = """Plot learning curves: success rate vs env steps and vs wall-clock minutes (two panels).

Each RUN is a `hydo train --out` folder; its eval.jsonl (one row per evaluation) is read and runs are
grouped by method (the algo in config.json): a line is the mean over the method's seeds, the band
their min-max. --heuristic draws the scripted heuristic's success rate as a dashed line (e.g. its
`hydo eval heuristic` figure). Needs the plot extra: pip install -e '.[plot]'.

Example:

  hydo plot runs/sweep/* --out curves.png --json curves.json --heuristic 0.54
"""

console = Console(stderr=True)


def plot(
    runs: Annotated[
        list[Path],
        typer.Argument(help="Training run folders (hydo train --out).", metavar="RUN", show_default=False),
    ],
    out: Annotated[
        Path, typer.Option("--out", help="Image to write (.png default; .pdf, .svg, .jpg by suffix).")
    ] = Path("curves.png"),
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Write the plotted curves as JSON here.")
    ] = None,
    heuristic: Annotated[
        float | None,
        typer.Option(
            "--heuristic", help="The scripted heuristic's success rate (0-1), drawn as a dashed line."
        ),
    ] = None,
    title: Annotated[str | None, typer.Option("--title", help="Figure title.")] = None,
) -> None:
    if heuristic is not None and not 0.0 <= heuristic <= 1.0:
        raise HydoError(f"--heuristic is a success rate in [0, 1], got {heuristic}")
    check_image_path("--out", out)
    for flag, path in (("--out", out), ("--json", json_out)):
        check_writable(flag, path)
    if len(set(runs)) != len(runs):
        raise HydoError("a RUN is given twice; give each run once")
    data = curves_data([load_run(r) for r in runs])
    fig = curves_figure(data, heuristic, title)
    if json_out is not None:
        atomic_write_text(json_out, json.dumps({"heuristic": heuristic, "methods": data}, indent=2))
        console.print(f"wrote {json_out}")
    save_figure(fig, out)
    summary = ", ".join(f"{d['name']}: {len(d['runs'])} runs" for d in data.values())
    console.print(f"wrote {out} ({summary})")
