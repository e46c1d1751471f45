"""``hydo eval``: success rate of a policy on held-out episodes, as a table and JSON.

TARGET is a built-in baseline (``heuristic``, ``random``), a training run directory or a checkpoint
(see ``hydo_cli.policies``). Evaluation is deterministic in its episodes (same seed, same objects,
starts and goals for every policy) and records whether the policy itself samples.
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console
from rich.table import Table

from hydo_cli.errors import HydoError
from hydo_cli.options import ClutterOpt, Goals, GoalsOpt, ObjectsOpt, ObsSource, SeedOpt
from hydo_cli.util import atomic_write_text

HELP = """Evaluate a policy: a run directory, a checkpoint, or a built-in baseline (heuristic, random).

Examples:

  hydo eval heuristic --goals planar --episodes 100

  hydo eval runs/hydo-cm-planar --objects unseen --episodes 100 --json results.json

  hydo eval heuristic --episodes 3 --video heuristic.mp4
"""

console = Console(stderr=True)


def make_envs(objects, goals, clutter, obs, n_envs, n_obj=None, n_bg=None, render=False):
    """``n_envs`` envs of one configuration (point counts default to the contract's)."""
    import sim  # noqa: F401  (registers hydo/Bin-v0)
    from sim.contract import DEFAULT_N_BG, DEFAULT_N_OBJ
    from sim.env import BinEnv
    from sim.objects import ObjectMeshError, load_objects

    try:
        assets = load_objects(objects)
    except ObjectMeshError:
        raise
    except ValueError as e:  # an unknown split or object name: say which forms are valid
        raise HydoError(str(e)) from None
    return [
        BinEnv(
            objects=assets,
            goals=goals,
            obs=obs,
            clutter=clutter,
            n_obj=n_obj or DEFAULT_N_OBJ,
            n_bg=n_bg or DEFAULT_N_BG,
            render_mode="rgb_array" if render else None,
        )
        for _ in range(n_envs)
    ]


def evaluate(
    target: Annotated[str, typer.Argument(help="heuristic | random | a run directory | a checkpoint file.")],
    objects: ObjectsOpt = "train",
    goals: GoalsOpt = Goals.planar,
    clutter: ClutterOpt = 0,
    episodes: Annotated[int, typer.Option("--episodes", help="Evaluation episodes.")] = 100,
    seed: SeedOpt = 0,
    obs: Annotated[ObsSource, typer.Option("--obs", help="Observation source.")] = ObsSource.mesh,
    json_out: Annotated[Path | None, typer.Option("--json", help="Write results as JSON here.")] = None,
    video: Annotated[Path | None, typer.Option("--video", help="Render the episodes to this .mp4.")] = None,
    video_episodes: Annotated[int, typer.Option(help="Episodes to render into --video.")] = 3,
) -> None:
    from hydo_cli.policies import load_policy
    from hydo_cli.rollout import run_episodes, summarize

    if episodes < 1:
        raise HydoError("--episodes must be at least 1")
    loaded = load_policy(target, seed=seed)
    n_obj, n_bg = loaded.n_obj, loaded.n_bg
    envs = make_envs(objects, goals.value, clutter, obs.value, 1, n_obj, n_bg, render=video is not None)
    frames: list = []
    on_frame = None
    if video is not None:
        if video.suffix.lower() != ".mp4":
            raise HydoError(f"--video must name an .mp4 file, got {video}")

        def on_frame(ep, rgb):
            if ep < video_episodes:
                frames.append(rgb)

    t0 = time.perf_counter()
    results = run_episodes(envs, loaded.policy, episodes, seed=seed, on_frame=on_frame)
    wall = time.perf_counter() - t0
    summary = summarize(results)
    summary.update(
        target=target,
        objects=objects,
        goals=goals.value,
        clutter=clutter,
        obs=obs.value,
        seed=seed,
        stochastic=loaded.stochastic,
        wall_s=wall,
        episodes_per_s=episodes / wall,
    )
    table = Table(title=f"hydo eval {target}  ({objects}, {goals.value} goals, {obs.value} obs)")
    for col in ("episodes", "success", "mean return", "steps to success", "rejected", "failures", "ep/s"):
        table.add_column(col)
    steps = summary["mean_steps_to_success"]
    table.add_row(
        str(episodes),
        f"{summary['success_rate']:.1%}",
        f"{summary['mean_return']:.3f}",
        "-" if steps is None else f"{steps:.1f}",
        str(summary["rejected_primitives"]),
        ", ".join(f"{k}: {v}" for k, v in summary["failures"].items()) or "-",
        f"{summary['episodes_per_s']:.1f}",
    )
    Console().print(table)
    if video is not None:
        from sim.render import write_video

        write_video(frames, video, fps=2)
        console.print(f"wrote {video} ({len(frames)} frames, {min(video_episodes, episodes)} episodes)")
    if json_out is not None:
        summary["episodes_detail"] = [r.as_dict() for r in results]
        atomic_write_text(json_out, json.dumps(summary, indent=2))
        console.print(f"wrote {json_out}")
