"""Pictures shared by the commands: learning curves (``hydo plot``), Table I as bars (``hydo eval
--compare --plot``) and the figure writer every picture goes through.

matplotlib is the optional ``plot`` extra: it is imported only when a picture is drawn, through the
object-oriented API (``matplotlib.figure.Figure``, no pyplot), so no GUI backend or global state is
touched. Every image is written atomically (``sim.atomic``: temp file + ``os.replace``); the format
follows the file's suffix (PNG by default).

Learning curves read what ``hydo train`` writes: ``config.json`` (``algo``) and ``eval.jsonl``, one
row per evaluation ``{env_steps, updates, wall_s, success_rate, mean_return, episodes}``.
"""

from __future__ import annotations

import json
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from hydo_cli.errors import HydoError
from hydo_cli.report import METHOD_NAMES, SPLIT_TITLES, method_key
from sim.atomic import atomic_write

#: Image formats a picture may be written as (by the output's suffix); no suffix means PNG.
IMAGE_SUFFIXES = {".png": "png", ".pdf": "pdf", ".svg": "svg", ".jpg": "jpg", ".jpeg": "jpg"}
DPI = 120
MINUTES_GRID = 60  # the vs-minutes panel resamples each method's seeds on this many points


def require_matplotlib():
    """``matplotlib.figure.Figure``, or one line that says how to install the ``plot`` extra."""
    try:
        from matplotlib.figure import Figure
    except ImportError:
        raise HydoError("pictures need matplotlib: pip install -e '.[plot]'") from None
    return Figure


def check_image_path(flag: str, path: Path) -> None:
    """Refuse, before any work, an image path of an unknown format (its folder is checked by the caller)."""
    if path.suffix and path.suffix.lower() not in IMAGE_SUFFIXES:
        raise HydoError(f"{flag} {path}: give a .png (default), .pdf, .svg or .jpg file")


def save_figure(fig, path: Path) -> Path:
    """Write ``fig`` to ``path`` atomically (temp file + ``os.replace``), PNG unless the suffix says."""
    fmt = IMAGE_SUFFIXES.get(path.suffix.lower(), "png")
    return atomic_write(path, lambda f: fig.savefig(f, format=fmt, dpi=DPI, bbox_inches="tight"))


def method_label(method: str) -> str:
    """The paper's name of a method (``hydo-cm`` -> ``HyDo + CM``)."""
    return METHOD_NAMES.get(method, method)


# --- learning curves ------------------------------------------------------------------------------


def load_run(run: Path) -> dict:
    """``{"run", "method", "config", "evals"}`` of a training run folder; one line if it is not one."""
    cfg_path, evals_path = run / "config.json", run / "eval.jsonl"
    if not run.is_dir():
        raise HydoError(f"RUN {run} is not a folder: give a `hydo train --out` folder")
    if not cfg_path.is_file() or not evals_path.is_file():
        missing = "config.json" if not cfg_path.is_file() else "eval.jsonl"
        raise HydoError(f"RUN {run} has no {missing}: give a `hydo train --out` folder with evaluations")
    try:
        cfg = json.loads(cfg_path.read_text())
        # a run cut mid-write may end in a torn line: its complete rows still count
        rows = []
        for line in evals_path.read_text().splitlines():
            if line.strip():
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    break
    except (OSError, json.JSONDecodeError) as e:
        raise HydoError(f"RUN {run}: cannot read {e}") from None
    if not rows:
        raise HydoError(f"RUN {run}: eval.jsonl has no evaluation yet")
    return {"run": str(run), "method": cfg.get("algo", "?"), "config": cfg, "evals": rows}


def group_by_method(runs: Sequence[dict]) -> dict[str, list[dict]]:
    """Runs per method (the run's algo), in Table I's row order."""
    groups: dict[str, list[dict]] = defaultdict(list)
    for r in runs:
        groups[r["method"]].append(r)
    return {m: groups[m] for m in sorted(groups, key=method_key)}


def steps_curve(runs: Sequence[dict]) -> list[dict]:
    """Success vs env steps: at each evaluation step, mean / min / max over the seeds evaluated there."""
    rows = []
    for s in sorted({e["env_steps"] for r in runs for e in r["evals"]}):
        at = [e for r in runs for e in r["evals"] if e["env_steps"] == s]
        sr = np.array([e["success_rate"] for e in at])
        rows.append(
            {
                "env_steps": int(s),
                "minutes_mean": float(np.mean([e["wall_s"] for e in at]) / 60),
                "success_mean": float(sr.mean()),
                "success_min": float(sr.min()),
                "success_max": float(sr.max()),
                "seeds": len(at),
                "episodes": int(at[0].get("episodes", 0)),
            }
        )
    return rows


def minutes_curve(runs: Sequence[dict], points: int = MINUTES_GRID, step: float | None = None) -> list[dict]:
    """Success vs wall-clock minutes: at each of ``points`` marks up to the longest run (or at every
    multiple of ``step`` minutes), every seed's latest evaluation at or before it (seeds with none yet
    are left out)."""
    longest = max(e["wall_s"] for r in runs for e in r["evals"]) / 60
    first = min(e["wall_s"] for r in runs for e in r["evals"]) / 60
    if step is not None:
        marks = [min(k * step, longest) for k in range(1, int(np.ceil(longest / step - 1e-9)) + 1)]
    else:
        marks = np.linspace(first, longest, points) if longest > first else [longest]
    rows = []
    for mark in marks:
        at = [[e for e in r["evals"] if e["wall_s"] / 60 <= mark + 1e-9] for r in runs]
        at = [a[-1] for a in at if a]
        if not at:
            continue
        sr = np.array([e["success_rate"] for e in at])
        rows.append(
            {
                "minutes": float(mark),
                "env_steps_mean": float(np.mean([e["env_steps"] for e in at])),
                "success_mean": float(sr.mean()),
                "success_min": float(sr.min()),
                "success_max": float(sr.max()),
                "seeds": len(at),
            }
        )
    return rows


def curves_data(runs: Sequence[dict]) -> dict:
    """What ``hydo plot`` draws (and writes with ``--json``): per method its runs and both curves."""
    return {
        m: {
            "name": method_label(m),
            "runs": [r["run"] for r in mine],
            "vs_env_steps": steps_curve(mine),
            "vs_minutes": minutes_curve(mine),
        }
        for m, mine in group_by_method(runs).items()
    }


def curves_figure(data: dict, heuristic: float | None = None, title: str | None = None):
    """Two panels, success rate vs env steps and vs wall-clock minutes: per method the seed mean and
    the min-max band over seeds; the scripted heuristic's level as a dashed line when given."""
    Figure = require_matplotlib()
    fig = Figure(figsize=(11, 4.2))
    axes = fig.subplots(1, 2, sharey=True)
    for k, d in enumerate(data.values()):
        colour = f"C{k}"
        for ax, rows, x in ((axes[0], d["vs_env_steps"], "env_steps"), (axes[1], d["vs_minutes"], "minutes")):
            xs = np.array([r[x] for r in rows], dtype=np.float64)
            mean = np.array([r["success_mean"] for r in rows])
            seeds = len(d["runs"])
            label = f"{d['name']} ({seeds} seed{'s' if seeds > 1 else ''})"
            ax.plot(xs, mean, color=colour, marker="o" if len(xs) < 12 else None, ms=3, label=label)
            ax.fill_between(
                xs,
                [r["success_min"] for r in rows],
                [r["success_max"] for r in rows],
                color=colour,
                alpha=0.2,
            )
    for ax, xlabel in zip(axes, ("env steps", "wall-clock minutes"), strict=True):
        if heuristic is not None:
            ax.axhline(heuristic, color="0.3", ls="--", lw=1, label="scripted heuristic")
        ax.set_xlabel(xlabel)
        ax.set_ylim(-0.02, 1.02)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("success rate (mean, band: min-max over seeds)")
    axes[1].legend(loc="best", fontsize=8)
    if title:
        fig.suptitle(title)
    return fig


# --- Table I --------------------------------------------------------------------------------------


def table1_figure(report: dict):
    """Table I as grouped bars: one group per split, one bar per method, height the IQM of the success
    rate across the method's runs and whiskers its 95 % CI (``report["aggregate"]`` of ``hydo eval``)."""
    Figure = require_matplotlib()
    methods = report["aggregate"]["methods"]
    splits = report["splits"]
    fig = Figure(figsize=(max(6.0, 1.2 * len(splits) * max(1, len(methods)) + 2), 4.2))
    ax = fig.subplots()
    width = 0.8 / max(1, len(methods))
    x = np.arange(len(splits))
    for k, m in enumerate(methods.values()):
        est = [m["splits"][s] for s in splits]
        iqm = np.array([e["iqm"] for e in est])
        lo = np.array([e["ci_low"] for e in est])
        hi = np.array([e["ci_high"] for e in est])
        pos = x - 0.4 + width * (k + 0.5)
        ax.bar(pos, iqm, width * 0.9, color=f"C{k}", label=f"{m['name']} ({len(m['targets'])} runs)")
        ax.errorbar(pos, iqm, yerr=[iqm - lo, hi - iqm], fmt="none", ecolor="black", capsize=3, lw=1)
    ax.set_xticks(x, [SPLIT_TITLES.get(s, s) for s in splits])
    ax.set_ylim(0, 1.05)
    ax.set_ylabel("success rate: IQM across runs, 95% CI")
    ax.set_title(f"Table I: {report['goals']} goals, {report['episodes']} episodes per run and split")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(loc="upper right", fontsize=8)
    return fig
