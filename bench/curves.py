"""Learning curves from training runs: success rate vs env steps and vs wall-clock minutes.

    python bench/curves.py runs/hydo-cm-* runs/hacman-* [--json curves.json]

Reads each run's ``eval.jsonl`` (written by ``hydo train`` at every evaluation) and ``config.json``,
groups runs by (algo, goals, objects, learner overrides), and prints per group the mean (min-max over
seeds) success rate at each evaluation step, with the wall-clock minutes at which it was measured, the
success rate vs wall-clock minutes (each seed's latest evaluation at or before every
``--minute-step``) and the plateau: each seed's mean success over its evaluations from
``--plateau-from`` minutes on (many evaluations of 50 episodes average out much of their noise).
``--windows 0,30,60,100,150`` also gives each seed's mean success over the evaluations inside each
window of wall-clock minutes (the "0–30 / 30–60 / ... min" figures of docs/results.md).
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from hydo_cli.figures import load_run, minutes_curve, steps_curve  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--json", type=Path, default=None)
    ap.add_argument("--minute-step", type=float, default=10.0, help="spacing of the vs-minutes table")
    ap.add_argument(
        "--plateau-from", type=float, default=8.0, help="minutes after which evaluations form the plateau"
    )
    ap.add_argument(
        "--windows",
        type=str,
        default=None,
        help="comma-separated wall-clock minutes, e.g. 0,30,60,100,150: each seed's mean success per window",
    )
    args = ap.parse_args()
    edges = _window_edges(args.windows) if args.windows else None
    from rich.console import Console
    from rich.table import Table

    from sim.atomic import atomic_write_text

    groups: dict[tuple, list[dict]] = defaultdict(list)
    for run in args.runs:
        if not (run / "eval.jsonl").exists():
            print(f"skipping {run}: no eval.jsonl", file=sys.stderr)
            continue
        r = load_run(run)
        c = r["config"]
        variant = ",".join(f"{k}={v}" for k, v in sorted(c.get("agent", {}).items()))
        groups[(c["algo"], c["goals"], c["objects"], variant)].append(r)
    out = {}
    console = Console()
    for (algo, goals, objects, variant), runs in sorted(groups.items()):
        if variant:
            algo = f"{algo}[{variant}]"
        table = Table(title=f"{algo}  {goals} goals  objects={objects}  ({len(runs)} seeds)")
        for col in ("env steps", "minutes (mean)", "success mean", "min", "max", "episodes/eval"):
            table.add_column(col, justify="right")
        curve = steps_curve(runs)
        for row in curve:
            table.add_row(
                str(row["env_steps"]),
                f"{row['minutes_mean']:.1f}",
                f"{row['success_mean']:.0%}",
                f"{row['success_min']:.0%}",
                f"{row['success_max']:.0%}",
                str(row["episodes"]),
            )
        console.print(table)
        by_minutes = minutes_curve(runs, step=args.minute_step)
        table = Table(title=f"{algo}  {goals} goals  objects={objects}: success vs wall-clock minutes")
        for col in ("minutes", "env steps (mean)", "success mean", "min", "max", "seeds"):
            table.add_column(col, justify="right")
        for row in by_minutes:
            table.add_row(
                f"{row['minutes']:.1f}",
                f"{row['env_steps_mean']:.0f}",
                f"{row['success_mean']:.0%}",
                f"{row['success_min']:.0%}",
                f"{row['success_max']:.0%}",
                str(row["seeds"]),
            )
        console.print(table)
        final = [r["evals"][-1] for r in runs if r["evals"]]
        plateau = [
            float(
                np.mean(
                    [e["success_rate"] for e in r["evals"] if e["wall_s"] >= 60 * args.plateau_from]
                    or [np.nan]
                )
            )
            for r in runs
        ]
        console.print(
            f"plateau (mean success of the evaluations from {args.plateau_from:g} min on), per seed: "
            + " / ".join(f"{p:.1%}" for p in plateau)
            + f"; mean {np.nanmean(plateau):.1%}"
        )
        windows = None
        if edges:
            windows = [window_means(r["evals"], edges) for r in runs]
            for r, w in zip(runs, windows, strict=True):
                console.print(
                    f"{Path(r['run']).name}: "
                    + " / ".join(
                        f"{x['from_min']:g}–{x['to_min']:g} min "
                        + ("–" if x["mean"] is None else f"{x['mean']:.1%} ({x['evaluations']})")
                        for x in w
                    )
                )
        out[f"{algo}/{goals}/{objects}"] = {
            "windows": windows,
            "runs": [r["run"] for r in runs],
            "plateau_from_min": args.plateau_from,
            "plateau": plateau,
            "curve": curve,
            "vs_minutes": by_minutes,
            "final": [
                {
                    "run": r["run"],
                    **{k: e[k] for k in ("env_steps", "updates", "wall_s", "success_rate", "episodes")},
                }
                for r, e in zip(runs, final, strict=True)
            ],
        }
    if args.json:
        atomic_write_text(args.json, json.dumps(out, indent=2))
        print(f"wrote {args.json}")


def _window_edges(text: str) -> list[float]:
    try:
        edges = [float(x) for x in text.split(",")]
    except ValueError:
        sys.exit(f"error: --windows takes comma-separated minutes, e.g. 0,30,60; got {text!r}")
    if len(edges) < 2 or any(b <= a for a, b in itertools.pairwise(edges)):
        sys.exit(f"error: --windows needs at least two increasing minutes; got {text!r}")
    return edges


def window_means(evals: list[dict], edges: list[float]) -> list[dict]:
    """Mean success of the evaluations whose ``wall_s`` lies in each ``[edges[i], edges[i+1])`` minutes
    window (the last one closed), with how many there were; ``mean`` None for an empty window."""
    out = []
    for i, (lo, hi) in enumerate(itertools.pairwise(edges)):
        last = i == len(edges) - 2
        inside = [
            e["success_rate"]
            for e in evals
            if lo * 60 <= e["wall_s"] and (e["wall_s"] <= hi * 60 if last else e["wall_s"] < hi * 60)
        ]
        mean = float(np.mean(inside)) if inside else None
        out.append({"from_min": lo, "to_min": hi, "mean": mean, "evaluations": len(inside)})
    return out


if __name__ == "__main__":
    main()
