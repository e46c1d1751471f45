"""``hydo eval``: evaluate one or more policies the way the paper does, as tables, JSON and Markdown.

Each TARGET is one *run*: a built-in baseline (``heuristic``, ``random``), a training run directory,
a checkpoint or an exported model folder (``hydo_cli.policies``). Every run faces the same episodes
(same seed: same objects, starts and goals); its environments are built for its own point counts.

Per run: success rate, mean primitives to success, per-object success and failure reasons. Across
runs: the interquartile mean (IQM) with a 95 % stratified bootstrap CI (``hydo_cli.stats``).
``--compare`` groups runs by method and lays out the paper's Table I; ``--task`` evaluates the
behaviour-diversity tasks of ``sim.tasks`` and reports behaviour entropy.
"""

from __future__ import annotations

import json
import shlex
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from hydo_cli.errors import HydoError
from hydo_cli.options import (
    ChainNoise,
    ClutterOpt,
    EvalWeights,
    Goals,
    GoalsOpt,
    ObjectsOpt,
    ObsSource,
    SeedOpt,
    TaskOpt,
)
from sim.atomic import atomic_write_text

HELP = """Evaluate policies: success per run, IQM [95% CI] across runs, the paper's Table I (--compare).

Each TARGET is one run: heuristic, random, a run directory, a checkpoint or an exported model folder.
Give several (e.g. the seeds of a method) to aggregate them. Every run faces the same episodes. The
policy acts as in training's evaluation (its `policy` column says whether it samples).

Per run: success rate, mean primitives to success, per-object success and failure reasons: `left bin`
and `timeout` (how failed episodes ended) and `refused` (failed episodes with at least one refused
primitive; they are counted under their end reason too). Across runs: interquartile mean (IQM,
scipy trim_mean 0.25) with a 95% percentile bootstrap CI, over runs stratified by split with 4 or
more runs per split; with fewer the IQM trims nothing (it is the mean of the runs) and the CI
resamples episodes within each run.

--compare groups runs by method (the algo in the run or manifest; baselines by name) and evaluates
every split: rows are methods, columns Unseen Category, Unseen Instance, Training Objects, cells
IQM [CI].

--task push-line | push-align (paper §V-C) starts the 6 cm cube at a fixed pose and reports the
behaviour entropy -sum_b pi(b) log_|B| pi(b) (0: one behaviour, 1: all equally often). push-line:
push the cube across the line y = 0; behaviour = 6 * face + sector of the first executed push, face
(0..3 = +x, +y, -x, -y side of the cube the contact lies on) and sector (six 60 deg sectors of the
horizontal motion around the face's inward normal: 0 straight in, 1/5 diagonal left/right, 2/4
sideways-away, 3 away). push-align: push the cube around a box to a pose turned 45 deg; behaviour
0 (passes above the box's centre line, y > 0) or 1 (below). README.md, section Evaluation.

Examples:

  hydo eval heuristic random --objects cube --episodes 20 --json eval.json --markdown eval.md

  hydo eval runs/hydo-s* runs/hacman-s* --compare --goals 6d --markdown table1.md

  hydo eval runs/hydo-push-line --task push-line --episodes 500
"""

console = Console(stderr=True)

#: Table I's columns, in the paper's order.
COMPARE_SPLITS = ("unseen-category", "unseen-instance", "train")
SPLIT_TITLES = {
    "unseen-category": "Unseen Category",
    "unseen-instance": "Unseen Instance",
    "train": "Training Objects",
}
#: The paper's method names (design.md §1), in Table I's row order; baselines after them.
METHOD_NAMES = {
    "hacman": "HACMan",
    "hacman-diff": "HACMan + Diff",
    "hacman-cm": "HACMan + CM",
    "hydo-gauss": "HyDo (w/o Diff)",
    "hydo": "HyDo",
    "hydo-cm": "HyDo + CM",
    "heuristic": "heuristic",
    "random": "random",
}


def make_envs(
    objects, goals, clutter, obs, n_envs, n_obj=None, n_bg=None, render=False, task=None, task_start="fixed"
):
    """``n_envs`` envs of one configuration (point counts default to the contract's).

    ``task`` (``sim.tasks``) replaces objects, goals and clutter by the task's scene; ``task_start``
    is ``fixed`` (evaluation) or ``random`` (training).
    """
    import sim  # noqa: F401  (registers hydo/Bin-v0)
    from sim.contract import DEFAULT_N_BG, DEFAULT_N_OBJ
    from sim.env import BinEnv
    from sim.objects import ObjectMeshError, load_objects

    if task is None:
        try:
            assets = load_objects(objects)
        except ObjectMeshError:
            raise
        except ValueError as e:  # an unknown split or object name: say which forms are valid
            raise HydoError(str(e)) from None
    else:
        assets = "cube"  # unused: the task names its object
    return [
        BinEnv(
            objects=assets,
            goals=goals,
            obs=obs,
            clutter=0 if task else clutter,
            n_obj=n_obj or DEFAULT_N_OBJ,
            n_bg=n_bg or DEFAULT_N_BG,
            render_mode="rgb_array" if render else None,
            task=task,
            task_start=task_start,
        )
        for _ in range(n_envs)
    ]


# --- per-run summaries ---------------------------------------------------------------------------
def failure_counts(results: Sequence) -> dict[str, int]:
    """Failed episodes by end reason, plus those with at least one refused primitive (overlapping)."""
    failed = [r for r in results if not r.success]
    return {
        "object_left_bin": sum(r.failure == "object_left_bin" for r in failed),
        "timeout": sum(r.failure == "timeout" for r in failed),
        "primitive_rejected": sum(r.rejected > 0 for r in failed),
    }


def run_summary(results: Sequence, task=None) -> dict:
    """Success, steps, failures, per-object breakdown (and behaviour entropy for a task) of one run."""
    from hydo_cli.rollout import summarize

    s = summarize(results)
    per_object: dict[str, list[bool]] = {}
    for r in results:
        per_object.setdefault(r.object, []).append(r.success)
    out = {
        "episodes": s["episodes"],
        "success_rate": s["success_rate"],
        "mean_steps_to_success": s["mean_steps_to_success"],
        "mean_return": s["mean_return"],
        "mean_final_distance_m": s["mean_final_distance_m"],
        "failures": failure_counts(results),
        "rejected_primitives": s["rejected_primitives"],
        "episodes_with_rejected": sum(r.rejected > 0 for r in results),
        "per_object": {
            k: {"episodes": len(v), "success_rate": float(np.mean(v))} for k, v in sorted(per_object.items())
        },
    }
    if task is not None:
        from sim.tasks import behaviour_entropy

        ids = behaviour_ids(results)
        counts = np.bincount(ids[ids >= 0], minlength=task.n_behaviours)
        out.update(
            behaviour_entropy=float(behaviour_entropy(ids, task.n_behaviours)),
            behaviours_seen=int((counts > 0).sum()),
            behaviour_counts={str(b): int(n) for b, n in enumerate(counts) if n},
            episodes_without_behaviour=int((ids < 0).sum()),
        )
    return out


def behaviour_ids(results: Sequence) -> np.ndarray:
    """Behaviour ids (n,) int, -1 where an episode has none."""
    return np.array([-1 if r.behaviour is None else r.behaviour for r in results], dtype=np.int64)


def method_key(method: str) -> tuple[int, str]:
    order = list(METHOD_NAMES)
    return (order.index(method) if method in order else len(order), method)


# --- aggregation ---------------------------------------------------------------------------------
def aggregate(runs: list[dict], splits: Sequence[str], seed: int, task=None) -> dict:
    """IQM [CI] across every run (strata: splits) and per method and split; entropy for a task."""
    from hydo_cli.stats import interval_estimate

    def successes(run):
        return np.array([e["success"] for e in run["episodes_detail"]], dtype=np.float64)

    def estimate(selected: list[dict], by_split: Sequence[str]) -> dict:
        strata = [[successes(r) for r in selected if r["objects"] == sp] for sp in by_split]
        return interval_estimate(strata, seed=seed).as_dict()

    def entropy_estimate(selected: list[dict]) -> dict:
        from sim.tasks import behaviour_entropy

        def score(ids, axis=-1):
            return behaviour_entropy(np.asarray(ids).astype(np.int64), task.n_behaviours, axis=axis)

        strata = [[behaviour_ids_from_detail(r).astype(np.float64) for r in selected]]
        return interval_estimate(strata, run_score=score, seed=seed, episode_bootstrap=False).as_dict()

    out = {"all": estimate(runs, splits), "methods": {}}
    methods = sorted({r["method"] for r in runs}, key=method_key)
    for m in methods:
        mine = [r for r in runs if r["method"] == m]
        entry = {
            "name": METHOD_NAMES.get(m, m),
            "targets": sorted({r["target"] for r in mine}, key=[r["target"] for r in mine].index),
            "splits": {sp: estimate(mine, [sp]) for sp in splits},
        }
        if task is not None:
            entry["behaviour_entropy"] = entropy_estimate(mine)
        out["methods"][m] = entry
    if task is not None:
        out["behaviour_entropy"] = entropy_estimate(runs)
    return out


def behaviour_ids_from_detail(run: dict) -> np.ndarray:
    return np.array(
        [-1 if e["behaviour"] is None else e["behaviour"] for e in run["episodes_detail"]], dtype=np.int64
    )


# --- rendering -----------------------------------------------------------------------------------
def _pct(x: float | None) -> str:
    return "-" if x is None else f"{x:.1%}"


def run_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """Header and rows of the per-run table (shared by the console and Markdown)."""
    compare, task = report["compare"], report["task"]
    header = ["run", "method"] + (["objects"] if compare else [])
    header += ["success", "steps to success", "left bin", "timeout", "refused", "refused prims"]
    header += (["entropy", "behaviours"] if task else []) + ["policy", "ep/s"]
    rows = []
    for r in report["runs"]:
        f = r["failures"]
        steps = r["mean_steps_to_success"]
        row = [r["target"], METHOD_NAMES.get(r["method"], r["method"])] + ([r["objects"]] if compare else [])
        row += [
            f"{r['success_rate']:.1%} ({round(r['success_rate'] * r['episodes'])}/{r['episodes']})",
            "-" if steps is None else f"{steps:.2f}",
            str(f["object_left_bin"]),
            str(f["timeout"]),
            str(f["primitive_rejected"]),
            str(r["rejected_primitives"]),
        ]
        if task:
            row += [
                f"{r['behaviour_entropy']:.3f}",
                f"{r['behaviours_seen']}/{report['task']['n_behaviours']}",
            ]
        row += ["stochastic" if r["stochastic"] else "deterministic", f"{r['episodes_per_s']:.1f}"]
        rows.append(row)
    return header, rows


def compare_rows(report: dict) -> tuple[list[str], list[list[str]]]:
    """Table I: method x split, each cell IQM [95% CI] of the success rate across that method's runs."""
    task = report["task"]
    splits = report["splits"]
    if task:
        header = ["Method", "Success", "Behaviour entropy", "Runs"]
    else:
        header = ["Method"] + [SPLIT_TITLES.get(s, s) for s in splits] + ["Runs"]
    rows = []
    for m in report["aggregate"]["methods"].values():
        cells = [cell(m["splits"][s]) for s in splits]
        if task:
            cells.append(cell(m["behaviour_entropy"]))
        rows.append([m["name"], *cells, str(len(m["targets"]))])
    return header, rows


def cell(e: dict) -> str:
    """``0.760 [0.718, 0.802]`` from an ``Estimate.as_dict()`` (``stats.Estimate.cell``)."""
    from hydo_cli.stats import format_cell

    return format_cell(e["iqm"], e["ci_low"], e["ci_high"])


def object_rows(report: dict, split: str) -> tuple[list[str], list[list[str]]]:
    runs = [r for r in report["runs"] if r["objects"] == split]
    objects = sorted({o for r in runs for o in r["per_object"]})
    header = ["object"] + [r["target"] for r in runs]
    rows = []
    for o in objects:
        cells = []
        for r in runs:
            p = r["per_object"].get(o)
            cells.append("-" if p is None else f"{p['success_rate']:.0%} ({p['episodes']})")
        rows.append([o, *cells])
    return header, rows


def rich_table(title: str, header: list[str], rows: list[list[str]]) -> Table:
    table = Table(title=title, title_justify="left")
    for h in header:
        table.add_column(h)
    for row in rows:
        table.add_row(*row)
    return table


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    def esc(c: str) -> str:
        return str(c).replace("|", "\\|")

    lines = ["| " + " | ".join(esc(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(esc(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def setup_line(report: dict) -> str:
    if report["task"]:
        where = f"task {report['task']['name']} (fixed start, |B| = {report['task']['n_behaviours']})"
    else:
        where = f"objects {', '.join(report['splits'])}, {report['goals']} goals, clutter {report['clutter']}"
    return (
        f"{where}; {report['obs']} observations; {report['episodes']} episodes per run and split; "
        f"seed {report['seed']}"
    )


def markdown_report(report: dict) -> str:
    """The whole report as Markdown: setup, Table I (--compare), runs, IQM, per-object success."""
    agg = report["aggregate"]
    out = ["# hydo eval", "", f"`{report['command']}`", "", setup_line(report) + ".", ""]
    if report["compare"]:
        title = "Behaviour diversity" if report["task"] else "Table I: success rate"
        out += [f"## {title}, IQM [95% CI] across runs", "", markdown_table(*compare_rows(report)), ""]
        for m in agg["methods"].values():
            line = f"- {m['name']} ({', '.join(m['targets'])}): {next(iter(m['splits'].values()))['note']}"
            if report["task"]:
                line += f"; behaviour entropy: {m['behaviour_entropy']['note'].split('; ', 1)[-1]}"
            out.append(line + ".")
        out.append("")
    out += ["## Runs", "", markdown_table(*run_rows(report)), ""]
    a = agg["all"]
    pooled = " (every method pooled: read the table above per method)" if report["compare"] else ""
    out += ["## Across all runs", "", f"Success rate IQM {cell(a)}{pooled}: {a['note']}.", ""]
    if report["task"]:
        e = agg["behaviour_entropy"]
        out += [f"Behaviour entropy IQM {cell(e)}: {e['note']}.", ""]
    for split in report["splits"]:
        header, rows = object_rows(report, split)
        if len(rows) > 1:
            out += [f"## Success per object: {split}", "", markdown_table(header, rows), ""]
    out += [
        "Columns: `left bin` / `timeout` count failed episodes by how they ended; `refused` counts failed "
        "episodes with at least one refused primitive (also counted under their end reason); "
        "`refused prims` counts refused primitives in all episodes. Statistics: `hydo_cli/stats.py`; "
        "behaviour descriptors: `sim/tasks.py`.",
        "",
    ]
    return "\n".join(out)


def print_report(report: dict) -> None:
    out = Console() if sys.stdout.isatty() else Console(width=160)  # logs and pipes: no 80-column wrap
    out.print(rich_table(f"hydo eval: {setup_line(report)}", *run_rows(report)))
    agg = report["aggregate"]
    if report["compare"]:
        title = "Behaviour diversity" if report["task"] else "Table I: success rate"
        out.print(rich_table(f"{title}, IQM [95% CI] across runs", *compare_rows(report)))
    else:
        for split in report["splits"]:
            header, rows = object_rows(report, split)
            if 1 < len(rows) <= 60:
                out.print(rich_table(f"success per object ({split})", header, rows))
    a = agg["all"]
    pooled = " (every method pooled)" if report["compare"] else ""
    out.print(f"success rate IQM across runs{pooled}: [bold]{cell(a)}[/]  ({a['note']})", highlight=False)
    if report["task"]:
        e = agg["behaviour_entropy"]
        out.print(f"behaviour entropy IQM across runs: [bold]{cell(e)}[/]", highlight=False)


# --- the command ---------------------------------------------------------------------------------
def evaluate(
    targets: Annotated[
        list[str],
        typer.Argument(
            help="One or more runs: heuristic | random | a run directory | a checkpoint | an exported model folder.",
            metavar="TARGET",
            show_default=False,
        ),
    ],
    objects: ObjectsOpt = "train",
    goals: GoalsOpt = Goals.planar,
    clutter: ClutterOpt = 0,
    episodes: Annotated[
        int, typer.Option("--episodes", help="Evaluation episodes per run (and split).")
    ] = 100,
    seed: SeedOpt = 0,
    obs: Annotated[ObsSource, typer.Option("--obs", help="Observation source.")] = ObsSource.mesh,
    compare: Annotated[
        bool,
        typer.Option(
            "--compare",
            help="Group runs by method and make the paper's Table I: evaluates unseen-category, "
            "unseen-instance and train (not with --objects).",
        ),
    ] = False,
    task: TaskOpt = None,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write the results as JSON here.")] = None,
    markdown_out: Annotated[
        Path | None, typer.Option("--markdown", help="Write the tables as Markdown here.")
    ] = None,
    video: Annotated[Path | None, typer.Option("--video", help="Render the episodes to this .mp4.")] = None,
    video_episodes: Annotated[int, typer.Option(help="Episodes to render into --video.")] = 3,
    feasible_only: Annotated[
        bool,
        typer.Option(
            "--feasible-only/--any-point",
            help="Learned policies choose among contact points whose push passes the workspace gate "
            "(as in training and deploy); --any-point takes the plain argmax (refused pushes cost a step).",
        ),
    ] = True,
    weights: Annotated[
        EvalWeights | None,
        typer.Option(
            "--weights",
            help="Weights a run or checkpoint acts with: average (the Polyak-averaged target networks) or "
            "online (the last gradient step's). Default: what the run was trained with (average unless "
            "its config says otherwise). Exported models hold the weights they were exported with.",
        ),
    ] = None,
    chain_noise: Annotated[
        ChainNoise | None,
        typer.Option(
            "--chain-noise",
            help="How a run's ddpm / cm chain acts: sample (its noise is the policy, as in the paper) or "
            "zero (the noiseless chain, deterministic). Default: the run's config (sample unless it says "
            "otherwise). Exported models act as they were exported.",
        ),
    ] = None,
) -> None:
    from hydo_cli.policies import load_policy
    from hydo_cli.rollout import run_episodes

    # 1. reconcile the flags before anything slow happens
    if episodes < 1:
        raise HydoError("--episodes must be at least 1")
    if len(set(targets)) != len(targets):
        dup = next(t for t in targets if targets.count(t) > 1)
        raise HydoError(f"TARGET '{dup}' is given twice; give each run once")
    if compare and objects != "train":
        raise HydoError(
            "--compare evaluates every split (unseen-category, unseen-instance, train); drop --objects"
        )
    if task is not None and (objects != "train" or clutter != 0 or goals != Goals.planar):
        raise HydoError(
            f"--task {task.value} fixes the object, goal and obstacles; drop --objects/--goals/--clutter"
        )
    if video is not None:
        if video.suffix.lower() != ".mp4":
            raise HydoError(f"--video must name an .mp4 file, got {video}")
        if len(targets) > 1 or compare:
            raise HydoError("--video records one run: give one TARGET and no --compare")
    task_def = None
    if task is not None:
        from sim.tasks import get_task

        task_def = get_task(task.value)
    splits = [task_def.name] if task_def else list(COMPARE_SPLITS) if compare else [objects]

    # 2. load every target first: a bad one fails in a second, not after the others ran
    w = None if weights is None else weights.value
    cn = None if chain_noise is None else chain_noise.value
    loaded = [
        load_policy(t, seed=seed, feasible_only=feasible_only, weights=w, chain_noise=cn) for t in targets
    ]

    # 3. run: same episodes for every run; envs per split and point counts
    frames: list = []
    on_frame = None
    if video is not None:

        def on_frame(ep, rgb):
            if ep < video_episodes:
                frames.append(rgb)

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    runs: list[dict] = []
    envs_cache: dict[tuple, list] = {}
    total_wall = 0.0
    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    ) as progress:
        for split in splits:
            for target, lp in zip(targets, loaded, strict=True):
                key = (split, lp.n_obj, lp.n_bg)
                if key not in envs_cache:
                    envs_cache[key] = make_envs(
                        split,
                        goals.value,
                        clutter,
                        obs.value,
                        1,
                        lp.n_obj,
                        lp.n_bg,
                        render=video is not None,
                        task=task.value if task else None,
                    )
                bar = progress.add_task(f"{target} ({split})", total=episodes)
                t0 = time.perf_counter()
                results = run_episodes(
                    envs_cache[key],
                    lp.policy,
                    episodes,
                    seed=seed,
                    on_frame=on_frame,
                    on_episode=lambda r, bar=bar: progress.advance(bar),
                )
                wall = time.perf_counter() - t0
                total_wall += wall
                progress.remove_task(bar)
                runs.append(
                    {
                        "target": target,
                        "method": lp.method or lp.description,
                        "description": lp.description,
                        "stochastic": lp.stochastic,
                        "n_obj": lp.n_obj,
                        "n_bg": lp.n_bg,
                        "objects": split,
                        **run_summary(results, task_def),
                        "wall_s": wall,
                        "episodes_per_s": episodes / wall,
                        "episodes_detail": [r.as_dict() for r in results],
                    }
                )
    for envs in envs_cache.values():
        for env in envs:
            env.close()

    # 4. aggregate, print, write
    agg = aggregate(runs, splits, seed, task_def)
    report = {
        "command": shlex.join(["hydo", *sys.argv[1:]]),
        "targets": list(targets),
        "splits": splits,
        "compare": compare,
        "feasible_only": feasible_only,
        "weights": w,
        "chain_noise": cn,
        "task": None
        if task_def is None
        else {
            "name": task_def.name,
            "summary": task_def.summary,
            "n_behaviours": task_def.n_behaviours,
            "behaviour_names": list(task_def.behaviour_names),
        },
        "goals": goals.value,
        "clutter": clutter,
        "obs": obs.value,
        "episodes": episodes,
        "seed": seed,
        "iqm": agg["all"]["iqm"],
        "ci_low": agg["all"]["ci_low"],
        "ci_high": agg["all"]["ci_high"],
        "aggregate": agg,
        "wall_s": total_wall,
        "episodes_per_s": len(runs) * episodes / total_wall,
        "runs": runs,
    }
    print_report(report)
    console.print(
        f"{len(runs) * episodes} episodes in {total_wall:.1f} s: {report['episodes_per_s']:.1f} episodes/s "
        f"({obs.value} observations, one process)"
    )
    if video is not None:
        from sim.render import write_video

        write_video(frames, video, fps=2)
        console.print(f"wrote {video} ({len(frames)} frames, {min(video_episodes, episodes)} episodes)")
    if json_out is not None:
        atomic_write_text(json_out, json.dumps(report, indent=2))
        console.print(f"wrote {json_out}")
    if markdown_out is not None:
        atomic_write_text(markdown_out, markdown_report(report))
        console.print(f"wrote {markdown_out}")
