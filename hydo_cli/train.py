"""``hydo train``: ``--workers`` processes (default 2, one per core), each stepping its share of the
envs and computing the gradient of its share of every batch (``hydo_cli.trainer``).

Run directory (``--out``)::

    config.json      the resolved configuration (preset < --config TOML < command-line flags)
    command.txt      the command line; system.json: package versions and machine
    metrics.jsonl    one line per log interval: env steps, updates, wall time, losses, temperatures
    eval.jsonl       periodic evaluation on held-out episodes (success rate, return)
    checkpoint.pt    latest checkpoint (atomic), also written at the end and on Ctrl-C
    replay.npz       a snapshot of worker 0's replay shard, and replay.sNNNNN.npz: what each later
                     checkpoint added (a new snapshot once those hold a shard's capacity), so a
                     checkpoint writes ~1 % of the shard; replay-1.*, worker-1.pt: worker 1's
                     shard and RNG states. --resume rebuilds the shards and continues where it stopped

``--resume`` continues the step counter, networks, optimisers, temperatures, RNG and replay buffer;
episodes in flight at the cut are restarted, and log rows written after the checkpoint are dropped.
A folder whose run was cut before its first checkpoint restarts from step 0.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import platform
import shlex
import sys
import time
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

from hydo_cli.config import PRESETS, Algo, TrainConfig, resolve_config
from hydo_cli.errors import HydoError
from hydo_cli.options import Goals, TaskOpt
from hydo_cli.paths import check_writable_folder
from sim.atomic import atomic_write_text

HELP = """Train a hybrid policy (HyDo or a baseline) in the simulated bin.

Examples:

  hydo train --preset quick                      # the README's few-minute run

  hydo train --algo hydo-cm --goals planar --objects train --steps 40000 --out runs/hydo-cm-planar

  hydo train --resume runs/hydo-cm-planar        # continue a cut run
"""

console = Console(stderr=True)


def system_info() -> dict[str, Any]:
    import importlib.metadata as md

    versions = {}
    for pkg in ("hydo", "torch", "mujoco", "numpy", "gymnasium", "onnx", "onnxruntime"):
        try:
            versions[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            versions[pkg] = None
    return {
        "python": sys.version,
        "platform": platform.platform(),
        "cpus": os.cpu_count(),
        "versions": versions,
    }


LOCK_FILE = "train.lock"


def hold_run_lock(run_dir: Path):
    """Lock ``run_dir/train.lock`` for this process (``fcntl.flock``: released by the kernel when the
    process ends, however it ends, so a killed run never leaves a stale lock). A second ``hydo train``
    (``--resume``) on the same run is refused in one line instead of both writing one checkpoint."""
    import fcntl

    path = run_dir / LOCK_FILE
    try:
        f = open(path, "a+")  # noqa: SIM115 - held open for the whole run
    except OSError as e:
        raise HydoError(f"{path}: cannot create the run's lock file ({e.strerror})") from None
    try:
        fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        f.seek(0)
        holder = f.read().strip() or "another process"
        f.close()
        raise HydoError(
            f"{run_dir} is being trained by another `hydo train` ({holder}, lock {path}): "
            "wait for it to finish or stop it first"
        ) from None
    f.seek(0)
    f.truncate()
    f.write(f"pid {os.getpid()}\n")
    f.flush()
    return f


def _default_out(cfg: TrainConfig) -> Path:
    return (
        Path("runs")
        / f"{cfg.algo}-{cfg.goals}-{cfg.objects.replace('/', '_')}-s{cfg.seed}-{time.strftime('%Y%m%d-%H%M%S')}"
    )


def train(
    algo: Annotated[
        Algo | None, typer.Option("--algo", help="Learner (design.md §1). [default: hydo-cm]")
    ] = None,
    goals: Annotated[
        Goals | None,
        typer.Option(
            "--goals", help="Goal mode: planar (translation) or 6d (stable pose). [default: planar]"
        ),
    ] = None,
    objects: Annotated[
        str | None, typer.Option("--objects", help="Object set, object name or mesh folder. [default: train]")
    ] = None,
    clutter: Annotated[
        int | None, typer.Option("--clutter", help="Extra scene objects: 0, 1, 2 or 5.")
    ] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Env steps (primitives) to train for.")] = None,
    seed: Annotated[int | None, typer.Option("--seed", help="Random seed.")] = None,
    denoise_steps: Annotated[int | None, typer.Option("--k", help="Denoising steps K (ddpm / cm).")] = None,
    task: TaskOpt = None,
    max_minutes: Annotated[
        float | None, typer.Option("--minutes", help="Wall-clock budget (0: none).")
    ] = None,
    workers: Annotated[
        int | None,
        typer.Option(
            "--workers",
            help="Data-parallel worker processes, one per core: 2 alone on 2 cores, 1 if two runs "
            "share them. [default: 2]",
        ),
    ] = None,
    threads: Annotated[
        int | None,
        typer.Option("--threads", help="torch threads per worker. [default: 1]"),
    ] = None,
    out: Annotated[
        Path | None, typer.Option("--out", help="Run directory (default: runs/<algo>-...).")
    ] = None,
    resume: Annotated[
        Path | None, typer.Option("--resume", help="Continue the run in this directory.")
    ] = None,
    fresh_replay: Annotated[
        bool,
        typer.Option(
            "--fresh-replay",
            help="On --resume, continue with an empty replay buffer if the saved one is missing.",
        ),
    ] = False,
    config: Annotated[Path | None, typer.Option("--config", help="TOML file of config keys.")] = None,
    preset: Annotated[str | None, typer.Option("--preset", help=f"One of {list(PRESETS)}.")] = None,
) -> None:
    if resume is not None:
        run_dir = Path(resume)
        if not (run_dir / "config.json").exists():
            raise HydoError(f"--resume {run_dir}: not a run directory (no config.json)")
        cfg = TrainConfig.load(run_dir / "config.json")
        fixed = {
            "--algo": algo, "--goals": goals, "--objects": objects, "--clutter": clutter, "--seed": seed,
            "--k": denoise_steps, "--task": task, "--config": config, "--preset": preset, "--out": out,
        }  # fmt: skip
        given = [flag for flag, value in fixed.items() if value is not None]
        if given:
            raise HydoError(
                f"--resume continues {run_dir} with its own config.json: drop {', '.join(given)} "
                "(only --steps, --minutes, --workers and --threads may change)"
            )
        changes: dict[str, Any] = {}
        if steps is not None:  # allow extending a finished run
            changes["steps"] = steps
        if max_minutes is not None:  # the budget counts the run's time over all its resumes
            changes["max_minutes"] = max_minutes
        if threads is not None:  # a speed setting, not a learning one: may differ on resume
            changes["threads"] = threads
        if workers is not None:  # the checkpoint's replay shards must match (the trainer checks)
            changes["workers"] = workers
        if changes:  # checked as the file is: --steps 0 or --workers 3 of 8 envs is one line
            cfg = cfg.replace(f"--resume {run_dir} with {', '.join(changes)}", **changes)
    else:
        cfg = resolve_config(
            preset,
            config,
            dict(
                algo=algo.value if algo else None,
                goals=goals.value if goals else None,
                objects=objects,
                clutter=clutter,
                steps=steps,
                seed=seed,
                denoise_steps=denoise_steps,
                max_minutes=max_minutes,
                threads=threads,
                workers=workers,
                task=task.value if task else None,
            ),
        )
        run_dir = out or _default_out(cfg)
        if run_dir.is_file():
            raise HydoError(f"--out {run_dir} is a file, not a folder")
        if (run_dir / "checkpoint.pt").exists():
            raise HydoError(f"{run_dir} already holds a run; use --resume {run_dir} or another --out")
        if any((run_dir / name).exists() for name in ("config.json", "metrics.jsonl", "eval.jsonl")):
            raise HydoError(
                f"{run_dir} holds a run cut before its first checkpoint; restart it with "
                f"--resume {run_dir} or choose another --out"
            )
    from hydo_cli.trainer import Trainer

    check_writable_folder("--resume" if resume is not None else "--out", run_dir)
    created = not run_dir.exists()
    run_dir.mkdir(parents=True, exist_ok=True)
    lock = hold_run_lock(run_dir)  # before the trainer reads (and on resume trims) the run's files
    try:
        trainer = Trainer(cfg, run_dir, resume=resume is not None, fresh_replay=fresh_replay)
    except BaseException:
        lock.close()
        if created:  # a refused new run leaves no folder behind (it held only the lock)
            (run_dir / LOCK_FILE).unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                run_dir.rmdir()
        raise
    # on --resume too: the run's record holds its current --steps / --minutes / --threads and the
    # full resolved agent configuration (trainer.cfg)
    atomic_write_text(run_dir / "config.json", json.dumps(dataclasses.asdict(trainer.cfg), indent=2))
    if resume is None:
        atomic_write_text(run_dir / "command.txt", shlex.join(["hydo", *sys.argv[1:]]) + "\n")
        atomic_write_text(run_dir / "system.json", json.dumps({**system_info(), **trainer.cpu}, indent=2))
    try:
        trainer.run(fresh_replay)
    finally:
        lock.close()  # releases the lock; the file stays (removing it would race a waiting process)
