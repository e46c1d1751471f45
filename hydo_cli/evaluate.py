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

import shlex
import sys
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from hydo_cli.envs import make_envs
from hydo_cli.errors import HydoError
from hydo_cli.options import (
    ChainNoise,
    ClutterOpt,
    Contacts,
    EvalWeights,
    Goals,
    ObjectsOpt,
    ObsSource,
    SeedOpt,
    TaskOpt,
)
from hydo_cli.paths import check_writable
from hydo_cli.records import is_record, load_record, recorded_runs, write_report
from hydo_cli.report import COMPARE_SPLITS, aggregate, run_summary
from hydo_cli.tables import markdown_report, print_report
from sim.atomic import atomic_write_text
from sim.contract import CONTACT_DEFAULT, CONTACT_MODELS, GOAL_MODES

HELP = """Evaluate policies: success per run, IQM [95% CI] across runs, the paper's Table I (--compare).

Each TARGET is one run: heuristic, random, a run directory, a checkpoint or an exported model folder;
or a recorded evaluation, FILE.json[.gz] written by `hydo eval --json` on the same episodes, whose
runs join this one without being rerun (a table whose runs were trained on different machines).
Give several (e.g. the seeds of a method) to aggregate them. Every run faces the same episodes. The
policy acts as in training's evaluation (its `policy` column says whether it samples). Goals are
the mode the runs were trained on (a model's manifest, a run's config) unless --goals says otherwise;
so is the scene's contact model (--contacts).

Per run: success rate, mean primitives to success, per-object success and failure reasons: `left bin`
and `timeout` (how failed episodes ended) and `refused` (failed episodes with at least one refused
primitive; they are counted under their end reason too), and `idle prims`, the share of primitives
that ran and left the object where it was (the fingers missed it). With 6D goals, `move` and `flip`: success
where the goal keeps the object's face up and where it asks for another face up (up to the object's
symmetry: a torus upside down is a move), and each object's
flips (the JSON's `by_goal` adds start and failed final distances, and flips onto a side against
flips turning the object over, at 120 deg, and the share of failures that end with another face
up than the goal's: for flips, the object never turned over; for the failures on the goal's face,
the median centroid offset and turn left, metres, and the share where the offset is the larger;
its `by_tilt` counts successes by the goal's tilt, 0-30 / 30-100 / 100-150 / 150-180 deg).
Across runs: interquartile mean (IQM, scipy trim_mean 0.25) with a 95% percentile bootstrap CI,
over runs stratified by split with 4 or more runs per split; with fewer the IQM trims nothing (it is the mean of the runs) and the CI
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

  hydo eval runs/6d/hydo-cm-s* runs/6d/hacman-s* heuristic --compare --markdown table1.md

  hydo eval runs/hydo-push-line --task push-line --episodes 500

  hydo eval docs/table1-6d/*.json.gz heuristic --compare --goals 6d --episodes 200 --seed 1
"""

console = Console(stderr=True)


def resolve_trained(
    option: str,
    given: str | None,
    trained_on: list[tuple[str, str | None]],
    default: str,
    choices: tuple[str, ...],
) -> str:
    """What the episodes are played in, for a setting a run is trained in (``--goals``, ``--contacts``):
    ``given`` if the option was given, else the one the learned targets were trained in or a record was
    evaluated in (a 6D model is not silently scored on planar goals, nor a run trained in HACMan's
    contacts in hydo's); ``default`` for baselines alone. ``trained_on``: ``(target,
    value or None)`` per target; targets that differ need the option."""
    if given is not None:
        return given
    trained = {t: v for t, v in trained_on if v is not None}
    if not trained:
        return default
    if len(set(trained.values())) > 1:
        listing = ", ".join(f"{t} ({v})" for t, v in trained.items())
        raise HydoError(
            f"the runs were trained with different --{option}: {listing}; give --{option} {'|'.join(choices)}"
        )
    return next(iter(trained.values()))


def evaluate(
    targets: Annotated[
        list[str],
        typer.Argument(
            help="One or more runs: heuristic | random | a run directory | a checkpoint | an exported model "
            "folder | a recorded evaluation FILE.json[.gz] (hydo eval --json on the same episodes).",
            metavar="TARGET",
            show_default=False,
        ),
    ],
    objects: ObjectsOpt = "train",
    goals: Annotated[
        Goals | None,
        typer.Option(
            "--goals",
            help="Goal mode: planar (translation only) or 6d. Default: the mode the runs were trained on "
            "(planar for baselines alone); runs trained on different modes need it.",
        ),
    ] = None,
    clutter: ClutterOpt = 0,
    episodes: Annotated[
        int, typer.Option("--episodes", help="Evaluation episodes per run (and split).")
    ] = 100,
    seed: SeedOpt = 0,
    obs: Annotated[ObsSource, typer.Option("--obs", help="Observation source.")] = ObsSource.mesh,
    contacts: Annotated[
        Contacts | None,
        typer.Option(
            "--contacts",
            help="The scene's contact model: hydo (its own) or hacman (HACMan's bin env's settings). "
            "Default: the one the runs were trained in (hydo for baselines alone).",
        ),
    ] = None,
    compare: Annotated[
        bool,
        typer.Option(
            "--compare",
            help="Group runs by method and make the paper's Table I: evaluates unseen-category, "
            "unseen-instance and train (not with --objects).",
        ),
    ] = False,
    task: TaskOpt = None,
    json_out: Annotated[
        Path | None,
        typer.Option("--json", help="Write the results as JSON here (gzip-compressed if it ends in .gz)."),
    ] = None,
    markdown_out: Annotated[
        Path | None, typer.Option("--markdown", help="Write the tables as Markdown here.")
    ] = None,
    plot_out: Annotated[
        Path | None,
        typer.Option(
            "--plot",
            help="With --compare: draw Table I as grouped bars (IQM, 95% CI whiskers) into this image "
            "(.png; needs the plot extra).",
        ),
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
    if task is not None and (objects != "train" or clutter != 0 or goals is not None):
        raise HydoError(
            f"--task {task.value} fixes the object, goal and obstacles; drop --objects/--goals/--clutter"
        )
    if video is not None:
        if video.suffix.lower() != ".mp4":
            raise HydoError(f"--video must name an .mp4 file, got {video}")
        if len(targets) > 1 or compare:
            raise HydoError("--video records one run: give one TARGET and no --compare")
    if plot_out is not None:
        from hydo_cli.figures import check_image_path, require_matplotlib

        if not compare:
            raise HydoError("--plot draws Table I: add --compare")
        check_image_path("--plot", plot_out)
        require_matplotlib()  # a missing extra fails now, not after the episodes
    for flag, path in (
        ("--json", json_out),
        ("--markdown", markdown_out),
        ("--plot", plot_out),
        ("--video", video),
    ):
        check_writable(flag, path)  # before the episodes run, so a bad path loses no results
    task_def = None
    if task is not None:
        from sim.tasks import get_task

        task_def = get_task(task.value)
    splits = [task_def.name] if task_def else list(COMPARE_SPLITS) if compare else [objects]

    # 2. load every target first: a bad one fails in a second, not after the others ran
    w = None if weights is None else weights.value
    cn = None if chain_noise is None else chain_noise.value
    records = {t: load_record(t) for t in targets if is_record(t)}
    if records and (task_def is not None or video is not None):
        raise HydoError("recorded evaluations (FILE.json) join goal evaluations only: drop --task/--video")
    live = [t for t in targets if t not in records]
    loaded = {
        t: load_policy(t, seed=seed, feasible_only=feasible_only, weights=w, chain_noise=cn) for t in live
    }
    trained = [(t, lp.goals) for t, lp in loaded.items()] + [(t, r["goals"]) for t, r in records.items()]
    given = None if goals is None else goals.value
    if task_def is not None and given is None:
        given = Goals.planar.value  # a task's episodes are planar (sim.tasks)
    goal_mode = resolve_trained("goals", given, trained, Goals.planar.value, GOAL_MODES)
    trained = [(t, lp.contacts) for t, lp in loaded.items()] + [
        (t, r["contacts"]) for t, r in records.items()
    ]
    contact_model = resolve_trained(
        "contacts", None if contacts is None else contacts.value, trained, CONTACT_DEFAULT, CONTACT_MODELS
    )
    for t, lp in loaded.items():  # a run plays in another contact model only when asked to
        if lp.contacts not in (None, contact_model):
            console.print(
                f"[yellow]note:[/] {t} was trained with contacts {lp.contacts}; this evaluation plays in "
                f"{contact_model}'s (--contacts {lp.contacts} to match)",
                soft_wrap=True,  # one line, whatever the terminal's width
            )
    settings = {"goals": goal_mode, "episodes": episodes, "seed": seed, "clutter": clutter}
    settings |= {"obs": obs.value, "feasible_only": feasible_only, "contacts": contact_model}
    recorded = {t: recorded_runs(t, r, settings, splits) for t, r in records.items()}
    seen: dict[tuple, str] = {}  # (target, split) → where it came from: a run pooled twice is refused
    for t in live:
        seen.update({(t, sp): t for sp in splits})
    for path, by_split in recorded.items():
        for sp, rs in by_split.items():
            for r in rs:
                if (r["target"], sp) in seen:
                    raise HydoError(
                        f"run {r['target']} on {sp} is in {path} and in {seen[r['target'], sp]}: give it once"
                    )
                seen[r["target"], sp] = path

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
            for target in targets:
                if target in recorded:  # its runs join as recorded, on the same episodes
                    runs.extend(recorded[target][split])
                    continue
                lp = loaded[target]
                key = (split, lp.n_obj, lp.n_bg)
                if key not in envs_cache:
                    envs_cache[key] = make_envs(
                        split,
                        goal_mode,
                        clutter,
                        obs.value,
                        1,
                        lp.n_obj,
                        lp.n_bg,
                        render=video is not None,
                        task=task.value if task else None,
                        contacts=contact_model,
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
                        "training": lp.training,
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
    n_played = sum(episodes for r in runs if "recorded" not in r)  # recorded runs were not rerun
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
        "goals": goal_mode,
        "clutter": clutter,
        "obs": obs.value,
        "contacts": contact_model,
        "episodes": episodes,
        "seed": seed,
        # one method: the IQM across its runs; several: None (per method under "aggregate")
        "iqm": None if agg["all"] is None else agg["all"]["iqm"],
        "ci_low": None if agg["all"] is None else agg["all"]["ci_low"],
        "ci_high": None if agg["all"] is None else agg["all"]["ci_high"],
        "aggregate": agg,
        "wall_s": total_wall,
        "episodes_per_s": n_played / total_wall if n_played else None,
        "runs": runs,
    }
    print_report(report)
    if n_played:
        console.print(
            f"{n_played} episodes in {total_wall:.1f} s: {report['episodes_per_s']:.1f} episodes/s "
            f"({obs.value} observations, one process)"
        )
    if recorded:
        n_rec = len(runs) - n_played // episodes
        console.print(f"{n_rec} runs read from {len(recorded)} recorded evaluations, not rerun")
    if json_out is not None:
        write_report(json_out, report)
        console.print(f"wrote {json_out}")
    if markdown_out is not None:
        atomic_write_text(markdown_out, markdown_report(report))
        console.print(f"wrote {markdown_out}")
    if plot_out is not None:
        from hydo_cli.figures import save_figure, table1_figure

        save_figure(table1_figure(report), plot_out)
        console.print(f"wrote {plot_out}")
    if video is not None:
        from sim.video import write_video

        write_video(frames, video, fps=2)
        console.print(f"wrote {video} ({len(frames)} frames, {min(video_episodes, episodes)} episodes)")
