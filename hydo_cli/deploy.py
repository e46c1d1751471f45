"""``hydo deploy``: run an exported ONNX policy on a Panda / FR3 with depth cameras, or on its MuJoCo twin.

Thin wiring: parse flags, build a ``robot.loop.DeployConfig``, run ``robot.loop.Deployment`` and
print a table. Torch is never imported on this path (numpy, onnxruntime, opencv, mujoco only).
Operator's checklist for a real arm: the external stop device within reach, a person watching,
``--dry-run`` first.
"""

from __future__ import annotations

import shlex
import sys
import time
from enum import Enum
from pathlib import Path
from typing import Annotated

import numpy as np
import typer
from rich.console import Console
from rich.table import Table

from hydo_cli.paths import check_writable, check_writable_folder

app = typer.Typer(invoke_without_command=True, no_args_is_help=False)  # help: the callback's docstring
err = Console(stderr=True)
out = Console()


class Robot(str, Enum):
    panda = "panda"
    fr3 = "fr3"
    sim = "sim"


class OnRefusal(str, Enum):
    stop = "stop"
    next_episode = "next-episode"


class Registration(str, Enum):  # robot.loop.REGISTRATIONS
    auto = "auto"
    views = "views"
    model = "model"


class Observe(str, Enum):  # robot.loop.OBSERVATIONS
    cloud = "cloud"
    model = "model"


RobotOpt = Annotated[
    Robot,
    typer.Option("--robot", help="panda (panda-python) | fr3 (franky) | sim (the MuJoCo twin of the cell)."),
]
CellOpt = Annotated[
    Path | None,
    typer.Option(
        "--cell",
        help="Cell file (cameras, bin, workspace, limits). Default: robot/cell.example.yaml (the twin's).",
    ),
]
BackgroundOpt = Annotated[
    Path | None,
    typer.Option(
        "--background",
        help="Empty-bin background. Default: background.npz next to the cell file (twin: captured).",
    ),
]


def _offset(text: str | None):
    if text is None:
        return None
    from robot.registration import parse_offset

    try:
        return parse_offset(text)
    except ValueError as e:
        raise typer.BadParameter(str(e)) from None


def _plan_table(episode: int, step: int, plan) -> None:
    t = Table(title=f"plan: episode {episode}, step {step} (dry run: nothing moves)", title_justify="left")
    for col in ("#", "kind", "move", "x (m)", "y (m)", "z (m)", "speed (m/s)"):
        t.add_column(col, justify="right" if col not in ("kind", "move") else "left")
    for row in plan.table_rows():
        t.add_row(*row)
    out.print(t)


@app.callback()
def deploy(
    ctx: typer.Context,
    robot: RobotOpt = Robot.sim,
    model: Annotated[
        Path | None, typer.Option("--model", help="Exported model folder (`hydo export`).")
    ] = None,
    cell: CellOpt = None,
    goal: Annotated[
        Path | None,
        typer.Option("--goal", help="Goal cloud from `hydo deploy capture-goal`. Twin default: sampled."),
    ] = None,
    goal_offset: Annotated[
        str | None,
        typer.Option(
            "--goal-offset",
            help="Planar goal DX,DY[,YAW_DEG]: the start cloud moved by metres / turned by degrees.",
        ),
    ] = None,
    background: BackgroundOpt = None,
    episodes: Annotated[int, typer.Option("--episodes", min=1, help="Episodes to run.")] = 1,
    max_steps: Annotated[int, typer.Option("--max-steps", min=1, help="Primitives per episode.")] = 10,
    log: Annotated[
        Path | None,
        typer.Option("--log", help="Session folder (new or empty). Default: runs/deploy/<time>-<robot>."),
    ] = None,
    dry_run: Annotated[
        bool,
        typer.Option(
            "--dry-run", help="Observe, decide and check; print each plan as a table; move nothing."
        ),
    ] = False,
    seed: Annotated[
        int, typer.Option("--seed", help="Seed of resampling, policy noise and twin episodes.")
    ] = 0,
    allow_no_realtime: Annotated[
        bool, typer.Option("--allow-no-realtime", help="Run a real arm without a PREEMPT_RT kernel (logged).")
    ] = False,
    on_refusal: Annotated[
        OnRefusal | None,
        typer.Option(
            "--on-refusal",
            help="A refused observation/plan stops the run, or ends the episode. "
            "Default: stop on real arms, next-episode in the twin (where it also applies to a reflex "
            "beyond the recovery limits; a real arm always stops the run then).",
        ),
    ] = None,
    replay: Annotated[
        Path | None,
        typer.Option(
            "--replay", help="Play a recorded session's frames back through perception and policy (dry run)."
        ),
    ] = None,
    objects: Annotated[
        str | None,
        typer.Option("--objects", help="Twin only: object set (default: the model's training objects)."),
    ] = None,
    speed_scale: Annotated[
        float,
        typer.Option(
            "--speed-scale",
            min=0.01,
            max=1.0,
            help="Slow every move by this factor (the cell's speeds are the maximum).",
        ),
    ] = 1.0,
    registration: Annotated[
        Registration,
        typer.Option(
            "--registration",
            help="views: the current cloud to the goal cloud; model: both to the object's mesh "
            "(the twin's object, or --object-mesh on a cell); auto: model for a 6D-goal policy in the "
            "twin or whenever --object-mesh is given, else views.",
        ),
    ] = "auto",
    object_mesh: Annotated[
        Path | None,
        typer.Option(
            "--object-mesh", help="The object's mesh (.obj / .stl, metres) for --registration model."
        ),
    ] = None,
    observe: Annotated[
        Observe | None,
        typer.Option(
            "--observe",
            help="What the policy sees of the object: cloud (the cameras' points, PCA normals) or model "
            "(the mesh at the registered pose, as in training; needs --registration model). "
            "Default: model with --registration model, else cloud.",
        ),
    ] = None,
) -> None:
    """Run an exported ONNX policy on a Franka arm with depth cameras, or on its MuJoCo twin.

    Observe -> ONNX policy -> safety check -> execute, until the goal (3 cm mean goal flow) or --max-steps. Every step is logged to a session folder; --dry-run prints each plan and moves nothing. On a real arm: keep the stop device within reach and run --dry-run first.

    Examples:

      hydo deploy --robot sim --model models/hydo-cm-planar --episodes 50

      hydo deploy --robot panda --model models/hydo-cm-6d --cell cell.yaml --goal goal.npz --dry-run

      hydo deploy capture-background --robot panda --cell cell.yaml
    """
    if ctx.invoked_subcommand is not None:
        return
    from robot.loop import DeployConfig, Deployment
    from robot.report import summary_lines, write_summary

    if model is None:
        raise typer.BadParameter(
            "--model is required (an exported model folder, from `hydo export`)", param_hint="--model"
        )
    if goal is not None and goal_offset is not None:
        raise typer.BadParameter("give --goal or --goal-offset, not both", param_hint="--goal-offset")
    check_writable_folder("--log", log)
    cfg = DeployConfig(
        robot=robot.value,
        model=model,
        cell=cell,
        goal=goal,
        goal_offset=_offset(goal_offset),
        background=background,
        episodes=episodes,
        max_steps=max_steps,
        log_dir=log,
        dry_run=dry_run or replay is not None,
        seed=seed,
        allow_no_realtime=allow_no_realtime,
        on_refusal=None if on_refusal is None else on_refusal.value,
        replay=replay,
        objects=objects,
        speed_scale=speed_scale,
        registration=Registration(registration).value,
        object_mesh=object_mesh,
        observe=None if observe is None else Observe(observe).value,
        command=shlex.join(["hydo", *sys.argv[1:]]),
    )
    dep = Deployment.prepare(cfg, printer=lambda msg: err.print(msg, highlight=False))
    if cfg.dry_run:
        dep.on_plan = _plan_table
    err.print(
        f"deploy: {cfg.robot}{' (dry run)' if cfg.dry_run else ''}, session {dep.log.folder}", highlight=False
    )
    try:
        result = dep.run()
    except KeyboardInterrupt:
        err.print("interrupted: motion stopped, cameras closed, log flushed")
        raise typer.Exit(130) from None
    write_summary(result)
    t = Table(title="hydo deploy", title_justify="left")
    t.add_column("")
    t.add_column("value", justify="right")
    for name, value in summary_lines(result):
        t.add_row(name, value)
    out.print(t)


def _twin_for_capture(cell, seed: int):
    from robot.twin import TwinWorld
    from sim.objects import load_objects

    world = TwinWorld(cell, seed=seed)
    world.load(load_objects("cube")[0])
    return world


@app.command("capture-background")
def capture_background_cmd(
    robot: RobotOpt = Robot.sim,
    cell: CellOpt = None,
    out_path: Annotated[
        Path | None, typer.Option("--out", help="Output file. Default: background.npz next to the cell file.")
    ] = None,
    frames: Annotated[
        int | None, typer.Option("--frames", min=1, help="Frames per camera (default: the cell's).")
    ] = None,
    seed: Annotated[int, typer.Option("--seed")] = 0,
) -> None:
    """Record the empty bin (per-pixel median depth of each camera).

    Empty the bin and put the arm at its home pose first: the background includes whatever the cameras see.

    Examples:

      hydo deploy capture-background --robot panda --cell cell.yaml

      hydo deploy capture-background --robot sim --out background.npz
    """
    from robot.cell import load_cell
    from robot.connect import open_cameras
    from robot.perception import capture_background

    c = load_cell(cell)
    path = out_path or Path(c.source).with_name("background.npz")
    world = None
    if robot is Robot.sim:
        world = _twin_for_capture(c, seed)
        world.hide_object()
    try:
        with open_cameras(c, robot.value, world=world) as cams:
            bg = capture_background(cams, c, frames)
    finally:
        if world is not None:
            world.close()
    bg.save(path)
    valid = np.mean([np.isfinite(d).mean() for d in bg.depth.values()])
    err.print(f"background of {len(bg.depth)} cameras ({valid:.0%} valid pixels) written to {path}")


@app.command("capture-goal")
def capture_goal_cmd(
    robot: RobotOpt = Robot.sim,
    cell: CellOpt = None,
    background: BackgroundOpt = None,
    out_path: Annotated[Path, typer.Option("--out", help="Output goal file.")] = Path("goal.npz"),
    offset: Annotated[
        str | None,
        typer.Option(
            "--offset",
            help="Planar goal DX,DY[,YAW_DEG] relative to where the object is now, instead of as-is.",
        ),
    ] = None,
    seed: Annotated[int, typer.Option("--seed", help="Twin: seed of the object's placement.")] = 0,
    object_name: Annotated[str, typer.Option("--object", help="Twin: the object to place.")] = "cube",
) -> None:
    """Record the object's cloud at the goal pose (goal.npz).

    Place the object where it should end up (or where it is now, with --offset), arm at home.

    Examples:

      hydo deploy capture-goal --robot panda --cell cell.yaml --out goal.npz

      hydo deploy capture-goal --robot panda --cell cell.yaml --offset 0.10,0.0,30 --out goal.npz
    """
    from robot.cell import load_cell
    from robot.connect import open_cameras
    from robot.perception import Background, capture_background, segment
    from robot.registration import Goal, goal_from_offset

    c = load_cell(cell)
    off = _offset(offset)
    world = None
    rng = np.random.default_rng(seed)
    try:
        if robot is Robot.sim:
            from robot.twin import sample_episode
            from sim.objects import load_objects

            world = _twin_for_capture(c, seed)
            asset = load_objects(object_name)[0]
            world.load(asset)
            world.hide_object()
        with open_cameras(c, robot.value, world=world) as cams:
            if world is not None:
                bg = Background.load(background, c) if background is not None else capture_background(cams, c)
                _, (pos, quat), _ = sample_episode(world, (asset,), "planar", rng)
                world.place_object(pos, quat)
            else:
                bg = Background.load(background or Path(c.source).with_name("background.npz"), c)
            seg = segment(cams.capture(), bg, c, rng)
    finally:
        if world is not None:
            world.close()
    goal = (
        goal_from_offset(seg.obj_points, *off) if off else Goal(seg.obj_points, "captured", None, time.time())
    )
    goal.save(out_path)
    centre = goal.points.mean(0)
    err.print(
        f"goal cloud of {len(goal.points)} points (centre {np.round(centre, 3).tolist()} m, base frame) written to {out_path}"
    )


@app.command("ladder")
def ladder_cmd(
    model: Annotated[Path, typer.Option("--model", help="Exported model folder (`hydo export`).")],
    episodes: Annotated[int, typer.Option("--episodes", min=1, help="Episodes per rung.")] = 100,
    seed: Annotated[
        int, typer.Option("--seed", help="Episode seed: rung episodes are `hydo eval --seed`'s episodes.")
    ] = 0,
    rungs: Annotated[
        str,
        typer.Option(
            "--rungs",
            help="Comma-separated rungs: env, env-render, twin-true, twin-cameras, twin (default: all).",
        ),
    ] = "env,env-render,twin-true,twin-cameras,twin",
    objects: Annotated[
        str | None, typer.Option("--objects", help="Object set (default: the model's training objects).")
    ] = None,
    log: Annotated[
        Path | None,
        typer.Option(
            "--log", help="Folder for the twin sessions and ladder.json. Default: runs/ladder/<time>."
        ),
    ] = None,
    json_out: Annotated[
        Path | None, typer.Option("--json", help="Also write the ladder's JSON here.")
    ] = None,
    jobs: Annotated[
        int,
        typer.Option(
            "--jobs",
            min=1,
            help="Processes: rungs run side by side, and each twin rung's episodes are split among "
            "them (the figures do not depend on it).",
        ),
    ] = 2,
    registration: Annotated[
        Registration,
        typer.Option(
            "--registration",
            help="The twin rung's registration: views, or model (the object's mesh, which the policy "
            "then observes at the fitted pose: --observe model); auto: model for a 6D-goal policy, "
            "else views (as hydo deploy).",
        ),
    ] = "auto",
    env_draws: Annotated[
        int,
        typer.Option(
            "--env-draws",
            min=1,
            help="Draws of the policy's sampling on the env rung: its success is one draw, the others "
            "give the spread a lower rung's loss is read against (a few seconds each).",
        ),
    ] = 5,
) -> None:
    """Where a policy's success is lost between training and the cell: the sim → twin ladder.

    Runs one exported model on the same episodes on five rungs, each adding one difference: the
    training env (mesh observations), the training env with rendered depth, the twin's full arm with
    true-pose observations, the twin observed through its cameras (true poses for the goal flow), the
    twin with cameras + segmentation + registration. Prints success, mean
    final distance and failure causes per rung, and scores the deploy loop's verdict against the truth.

    Examples:

      hydo deploy ladder --model models/hydo-cm-planar --episodes 100 --seed 3

      hydo deploy ladder --model models/hydo-cm-6d --rungs env,twin --episodes 50
    """
    import json

    from hydo_cli.ladder import RUNGS, ladder_json, run_ladder
    from robot.onnx_policy import OnnxPolicy
    from sim.atomic import atomic_write_text

    chosen = tuple(r.strip() for r in rungs.split(",") if r.strip())
    bad = [r for r in chosen if r not in RUNGS]
    if bad or not chosen:
        raise typer.BadParameter(f"rungs are {', '.join(RUNGS)}; got {rungs!r}", param_hint="--rungs")
    chosen = tuple(r for r in RUNGS if r in chosen)  # ladder order
    OnnxPolicy.load(model)  # a bad model folder is one line, before any rung starts
    folder = log if log is not None else Path("runs") / "ladder" / time.strftime("%Y%m%d-%H%M%S")
    check_writable_folder("--log", folder)
    check_writable("--json", json_out)
    folder.mkdir(parents=True, exist_ok=True)
    err.print(f"ladder: {', '.join(chosen)}; {episodes} episodes each, seed {seed}; logs in {folder}")
    t0 = time.time()
    try:
        results = run_ladder(
            model, episodes, seed, folder, chosen, objects, jobs, Registration(registration).value, env_draws
        )
    except KeyboardInterrupt:
        err.print("interrupted")
        raise typer.Exit(130) from None
    doc = ladder_json(results, shlex.join(["hydo", *sys.argv[1:]]), model, seed)
    doc["wall_s"] = round(time.time() - t0, 1)
    text = json.dumps(doc, indent=2)
    atomic_write_text(folder / "ladder.json", text)
    if json_out is not None:
        atomic_write_text(json_out, text)
    t = Table(title=f"sim -> twin ladder: {model}, {episodes} episodes, seed {seed}", title_justify="left")
    cols = ("rung", "success", "dist", "lost/won", "near", "limit", "left", "refused", "force", "reflex")
    for col in cols:
        t.add_column(col, justify="left" if col == "rung" else "right")
    for s in doc["rungs"]:
        c = s["causes"]
        refused = sum(v for k, v in c.items() if k.endswith(("Error", "Rejected")))
        lg = f"-{s['lost_vs_previous']}/+{s['gained_vs_previous']}" if "lost_vs_previous" in s else ""
        t.add_row(
            s["rung"],
            f"{s['success_rate']:.0%}",
            f"{s['mean_final_distance_m'] * 100:.1f} cm",
            lg,
            str(c.get("near_miss", 0)),
            str(c.get("step_limit", 0)),
            str(c.get("object_left_bin", 0)),
            str(refused),
            str(s["force_stops"]),
            str(s["reflexes"] + c.get("reflex_limit", 0)),
        )
    out.print(t)
    out.print(
        "dist: mean final distance; lost/won: episodes vs the rung above; failed episodes by what ended "
        "them: near (step limit within 3-4.5 cm), limit (step limit), left (the bin), refused (a refusal; "
        "kinds below); force: contact-force stops; reflex: reflexes (+ episodes ended by the reflex limit)"
    )
    for s in doc["rungs"]:
        if "policy_draws" in s:
            rates = s["policy_draws"]
            out.print(
                f"{s['rung']} over {len(rates)} draws of the policy's sampling: mean "
                f"{s['policy_draws_mean']:.1%} ({min(rates):.0%}-{max(rates):.0%}); the table's is the first"
            )
    for s in doc["rungs"]:
        kinds = {k: v for k, v in s["causes"].items() if k.endswith(("Error", "Rejected"))}
        if kinds or s["refused_primitives"]:
            out.print(
                f"refusals ({s['rung']}): "
                + ", ".join(
                    [f"{k} {v}" for k, v in kinds.items()] + [f"refused primitives {s['refused_primitives']}"]
                )
            )
    for s in doc["rungs"]:
        v = s.get("verdict")
        if v:
            agree = "n/a" if v["agreement"] is None else f"{v['agreement']:.0%}"
            out.print(
                f"deploy verdict ({s['rung']}): reports {v['reported_success_rate']:.0%} success; agrees with "
                f"the true pose on {agree} of decided episodes; {v['ambiguous']} ambiguous; "
                f"{v['false_success']} false successes ({v['false_success_symmetric']} symmetric poses), "
                f"{v['false_failure']} false failures"
            )
    err.print(f"ladder.json written to {folder}")
