"""``hydo sweep``: the paper's protocol (methods x seeds x one configuration) as one command.

Every *trial* is one ordinary ``hydo train`` run, launched as its own process
(``python -m hydo_cli.main train ...``) into ``DIR/<algo>-s<seed>``: the folder holds exactly what
``hydo train --out`` writes, so ``hydo eval``, ``hydo plot`` and ``hydo export`` read it as any run.
A trial whose folder already holds a run is continued with ``hydo train --resume`` (from its last
``checkpoint.pt``; a run cut before its first checkpoint restarts), so re-running the same sweep
after a crash, a Ctrl-C or a lost node finishes what is left and never repeats finished trials.

Sweep-level bookkeeping lives beside the runs, never in them::

    DIR/sweep.json            the sweep's command and each trial's state (pending/running/done/failed)
    DIR/logs/<trial>.log      each trial's console output (all attempts, appended)
    DIR/logs/<trial>.pid      the running attempt's process id

Locally the trials run as at most ``--jobs`` processes at a time (a plain process pool: default
cores // (workers x threads)). With ``--ray ADDRESS`` (or ``auto``) they run on an existing Ray cluster
through Ray Tune (the ``cluster`` extra): one Tune trial per hydo trial, reserving
``workers x threads`` CPUs; a trial whose node fails is retried (``--max-failures``) and resumes
from its checkpoint. On a cluster ``DIR`` must be a path every node sees (a shared filesystem).
"""

from __future__ import annotations

import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import typer
from pydantic import BaseModel, Field, ValidationError
from rich.console import Console

from hydo_cli.errors import HydoError
from hydo_cli.options import Goals, TaskOpt
from models.choices import ALGOS
from sim.atomic import atomic_write_text
from sim.schema import STRICT, one_line

HELP = """Run methods x seeds as ordinary `hydo train` runs DIR/<algo>-s<seed>, locally or on a Ray cluster.

Each trial is `hydo train --algo A --seed S --out DIR/A-sS` plus the shared train flags (--config or
--preset, --steps, --minutes, --goals, --objects, ...). Running the same command again resumes
unfinished trials (hydo train --resume) and skips finished ones. When all are done it prints the
`hydo eval --compare` command over them (--compare-episodes N runs it).

Locally: at most --jobs trials at a time, each with --workers x --threads cores. --ray ADDRESS|auto:
on an existing Ray cluster through Ray Tune (pip install -e '.[cluster]'), one trial per task with
its CPU count; DIR must be on a filesystem every node sees.

Examples:

  hydo sweep --algos hydo-cm,hacman --seeds 0,1,2 --config configs/planar-train.toml --out runs/sweep

  hydo sweep --algos hydo-cm,hacman --seeds 0,1,2,3 --preset default --minutes 60 --ray auto --out /shared/sweep
"""

console = Console(stderr=True)
#: Training flags a sweep passes to every trial (``hydo train --help``); the first group also on resume.
RESUME_FLAGS = ("--steps", "--minutes")
TRAIN_FLAGS = (*RESUME_FLAGS, "--config", "--preset", "--goals", "--objects", "--clutter", "--k", "--task")
POLL_S = 1.0  # how often progress is read from the runs' metrics.jsonl


@dataclass(frozen=True)
class Trial:
    """One run of the sweep: method ``algo``, ``seed``, its folder and the command that (re)starts it."""

    algo: str
    seed: int
    run: Path
    log: Path

    @property
    def name(self) -> str:
        return f"{self.algo}-s{self.seed}"

    def command(self, train_args: list[str], resume_args: list[str]) -> list[str]:
        """``hydo train`` for a new run, or ``--resume`` where the folder already holds one (config.json:
        the trainer restarts a run cut before its first checkpoint itself)."""
        base = [sys.executable, "-m", "hydo_cli.main", "train"]
        if (self.run / "config.json").exists():
            return [*base, "--resume", str(self.run), *resume_args]
        return [*base, "--algo", self.algo, "--seed", str(self.seed), "--out", str(self.run), *train_args]


#: run_local marks trials from its pool threads: without one lock over update and write, a thread that
#: serialised the state before another's update could write after it, and a finished trial would read
#: as running. Module-level, not a field: Ray pickles the spec for its trials, and a lock does not pickle.
_MARK_LOCK = threading.Lock()


@dataclass
class SweepSpec:
    """What every trial is given: the train flags, the per-trial cores and where it all goes."""

    out: Path
    trials: list[Trial]
    train_args: list[str]
    resume_args: list[str]
    cpus: int  # per trial: workers x threads
    state: dict = field(default_factory=dict)

    # --- sweep.json: each trial's state, written by the driver only -----------------------------
    def load_state(self) -> None:
        """Read ``sweep.json`` (:class:`SweepFile`); one line naming the file and key if it is damaged
        (a trial marked done is skipped, so a wrong state must never be guessed)."""
        path = self.out / "sweep.json"
        if path.exists():
            self.state = read_sweep_file(path)

    def mark(self, trial: Trial, status: str, **extra) -> None:
        with _MARK_LOCK:  # update and write as one step
            entry = self.state.setdefault(trial.name, {"attempts": 0})
            entry.update(status=status, run=str(trial.run), **extra)
            if status == "running":
                entry["attempts"] += 1
            doc = {"command": shlex.join(["hydo", *sys.argv[1:]]), "trials": self.state}
            atomic_write_text(self.out / "sweep.json", json.dumps(doc, indent=2))

    def pending(self) -> list[Trial]:
        return [t for t in self.trials if self.state.get(t.name, {}).get("status") != "done"]


TrialStatus = Literal["pending", "running", "done", "failed"]


class TrialState(BaseModel):
    """One trial's entry of ``sweep.json`` (written by ``SweepSpec.mark``)."""

    model_config = STRICT

    status: TrialStatus
    run: Annotated[str, Field(min_length=1)]
    attempts: Annotated[int, Field(ge=0)]
    returncode: int | None = None


class SweepFile(BaseModel):
    """``DIR/sweep.json``: the sweep's command and each trial's state, by trial name (``algo-sSEED``)."""

    model_config = STRICT

    command: str
    trials: dict[str, TrialState]


def read_sweep_file(path: Path) -> dict:
    """``sweep.json``'s trial states as plain dicts, or a ``HydoError`` line naming the file and key."""
    hint = f"fix it or delete it (the runs in {path.parent} are kept and resume)"
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise HydoError(f"{path}: not readable sweep bookkeeping ({type(e).__name__}): {hint}") from None
    if not isinstance(doc, dict):
        raise HydoError(f"{path}: must be a JSON object, got {type(doc).__name__}: {hint}")
    try:
        parsed = SweepFile(**doc)
    except ValidationError as e:
        raise HydoError(f"{one_line(e, str(path))}: {hint}") from None
    return {name: t.model_dump(exclude_none=True) for name, t in parsed.trials.items()}


def progress_of(run: Path) -> tuple[int, int]:
    """``(env steps done, env steps planned)`` of a run from its metrics.jsonl and config.json (0s if none)."""
    try:
        planned = int(json.loads((run / "config.json").read_text()).get("steps", 0))
    except (OSError, ValueError):
        planned = 0
    done = 0
    try:
        with open(run / "metrics.jsonl", "rb") as f:
            f.seek(max(0, os.fstat(f.fileno()).st_size - 4096))  # the last lines are enough
            for line in f.read().splitlines()[::-1]:
                try:
                    done = int(json.loads(line)["env_steps"])
                    break
                except (ValueError, KeyError):
                    continue
    except OSError:
        pass
    return done, planned


def _death_signal():
    """A ``preexec_fn`` that makes the child get SIGTERM when the thread that started it dies (Linux
    ``PR_SET_PDEATHSIG``), so a killed sweep or Ray worker never leaves a training process running on
    its own (SIGTERM: it checkpoints first). libc is loaded here, in the parent: the child, forked
    from a threaded process, only makes the one C call."""
    if not sys.platform.startswith("linux"):
        return None
    import ctypes

    prctl = ctypes.CDLL(None, use_errno=True).prctl
    PR_SET_PDEATHSIG = 1
    return lambda: prctl(PR_SET_PDEATHSIG, int(signal.SIGTERM))


def run_trial(trial: Trial, spec: SweepSpec, stop: threading.Event | None = None) -> int:
    """Run (or resume) one trial to its end as a child process; returns its exit status.

    Output is appended to ``trial.log``; the child's pid is in ``logs/<trial>.pid`` while it runs.
    """
    cmd = trial.command(spec.train_args, spec.resume_args)
    trial.log.parent.mkdir(parents=True, exist_ok=True)
    pid_file = trial.log.with_suffix(".pid")
    with open(trial.log, "ab") as log:
        log.write(f"\n[hydo sweep {time.strftime('%Y-%m-%d %H:%M:%S')}] {shlex.join(cmd)}\n".encode())
        log.flush()
        proc = subprocess.Popen(
            cmd, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, preexec_fn=_death_signal()
        )
        atomic_write_text(pid_file, f"{proc.pid}\n")
        try:
            while proc.poll() is None:
                if stop is not None and stop.is_set():
                    proc.send_signal(signal.SIGTERM)  # the trainer checkpoints on SIGTERM, then exits
                try:
                    proc.wait(timeout=POLL_S)
                except subprocess.TimeoutExpired:
                    pass
        except BaseException:
            proc.send_signal(signal.SIGTERM)
            proc.wait()
            raise
        finally:
            pid_file.unlink(missing_ok=True)
    return proc.returncode


# --- local: a plain process pool -----------------------------------------------------------------


def run_local(spec: SweepSpec, jobs: int) -> dict[str, int]:
    """At most ``jobs`` trials at a time; a rich bar per trial (env steps from its metrics.jsonl)."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    pending = spec.pending()
    stop = threading.Event()
    results: dict[str, int] = {}
    with (
        Progress(
            TextColumn("{task.description:<18}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("env steps  {task.fields[status]}"),
            TimeElapsedColumn(),
            console=console,
        ) as progress,
        ThreadPoolExecutor(max_workers=jobs) as pool,
    ):
        bars = {t.name: progress.add_task(t.name, total=None, status="queued") for t in pending}

        def one(trial: Trial) -> int:
            if stop.is_set():
                return 130
            spec.mark(trial, "running")
            progress.update(bars[trial.name], status="running")
            rc = run_trial(trial, spec, stop)
            spec.mark(trial, "done" if rc == 0 else "failed", returncode=rc)
            progress.update(bars[trial.name], status="done" if rc == 0 else f"failed (exit {rc})")
            return rc

        futures = {t.name: pool.submit(one, t) for t in pending}
        try:
            while not all(f.done() for f in futures.values()):
                for t in pending:
                    done, planned = progress_of(t.run)
                    progress.update(bars[t.name], completed=done, total=planned or None)
                time.sleep(POLL_S)
        except KeyboardInterrupt:
            stop.set()  # every running trial gets SIGTERM and writes its checkpoint
            console.print(
                "stopping: each running trial writes its checkpoint; run the same command to resume"
            )
            for f in futures.values():
                f.result()
            raise
        for t in pending:
            done, planned = progress_of(t.run)
            progress.update(bars[t.name], completed=done, total=planned or None)
            results[t.name] = futures[t.name].result()
    return results


# --- Ray Tune ------------------------------------------------------------------------------------


def _tune_trainable(config: dict, spec: SweepSpec) -> None:
    """A Tune function trainable: runs one hydo trial as a child process and reports its env steps.

    A non-zero exit raises, so Tune retries the trial (``FailureConfig``); the retry resumes the run
    from its checkpoint (``Trial.command``)."""
    from ray import tune

    trial = next(t for t in spec.trials if t.name == config["trial"])
    box: dict = {}
    worker = threading.Thread(target=lambda: box.setdefault("rc", run_trial(trial, spec)), daemon=True)
    worker.start()
    while worker.is_alive():
        worker.join(timeout=5 * POLL_S)
        done, planned = progress_of(trial.run)
        tune.report({"env_steps": done, "planned_steps": planned})
    if box.get("rc", 1) != 0:
        raise RuntimeError(f"hydo train exited with {box.get('rc')}: see {trial.log}")


def _mark_trials(spec: SweepSpec, results: dict[str, int]):
    """A Tune callback (in the driver) that keeps sweep.json and the console in step with the trials."""
    from ray import tune

    class MarkTrials(tune.Callback):
        # Tune pickles its callbacks with the experiment state: hold only picklable things (no console)
        def __init__(self, spec, results):
            self.spec, self.results = spec, results

        def trial(self, trial) -> Trial:
            return next(t for t in self.spec.trials if t.name == trial.config["trial"])

        def on_trial_start(self, iteration, trials, trial, **info):
            self.spec.mark(self.trial(trial), "running")

        def on_trial_recover(self, iteration, trials, trial, **info):  # failed; Tune retries it
            _say(f"{trial.config['trial']}: failed, retrying (it resumes from its checkpoint)")

        def on_trial_result(self, iteration, trials, trial, result, **info):
            _say(f"{trial.config['trial']}: {result['env_steps']}/{result['planned_steps']} env steps")

        def on_trial_complete(self, iteration, trials, trial, **info):
            self.spec.mark(self.trial(trial), "done", returncode=0)
            self.results[trial.config["trial"]] = 0

        def on_trial_error(self, iteration, trials, trial, **info):
            self.spec.mark(self.trial(trial), "failed", returncode=1)
            self.results[trial.config["trial"]] = 1

    return MarkTrials(spec, results)


def _say(text: str) -> None:
    console.print(text)


def run_ray(spec: SweepSpec, address: str, max_failures: int) -> dict[str, int]:
    """Every pending trial as one Tune trial reserving ``spec.cpus`` CPUs on the cluster at ``address``."""
    try:
        import ray
        from ray import tune
    except ImportError:
        raise HydoError("--ray needs Ray Tune: pip install -e '.[cluster]'") from None

    if not ray.is_initialized():
        try:
            ray.init(address=address, log_to_driver=False)
        except Exception as e:  # Ray raises ConnectionError, RuntimeError or its own: all mean "not there"
            raise HydoError(f"--ray {address}: cannot connect to a Ray cluster there ({e})") from None
    pending = spec.pending()
    results: dict[str, int] = {}
    tuner = tune.Tuner(
        tune.with_resources(tune.with_parameters(_tune_trainable, spec=spec), {"cpu": spec.cpus}),
        param_space={"trial": tune.grid_search([t.name for t in pending])},
        tune_config=tune.TuneConfig(reuse_actors=False),
        run_config=tune.RunConfig(
            name=f"sweep-{time.strftime('%Y%m%d-%H%M%S')}",
            storage_path=str((spec.out / "ray").absolute()),
            failure_config=tune.FailureConfig(max_failures=max_failures),
            callbacks=[_mark_trials(spec, results)],
            verbose=0,
        ),
    )
    tuner.fit()
    for t in pending:
        results.setdefault(t.name, 1)
    return results


# --- the command ---------------------------------------------------------------------------------


def _csv(flag: str, text: str) -> list[str]:
    items = [x.strip() for x in text.split(",") if x.strip()]
    if not items:
        raise HydoError(f"{flag} is empty: give a comma-separated list")
    if len(set(items)) != len(items):
        raise HydoError(f"{flag} {text}: an item is given twice")
    return items


def eval_command(spec: SweepSpec, episodes: int | None = None) -> list[str]:
    """The ``hydo eval --compare`` command over the sweep's runs (with its goal mode)."""
    cmd = ["hydo", "eval", *[str(t.run) for t in spec.trials], "--compare"]
    try:
        goals = json.loads((spec.trials[0].run / "config.json").read_text())["goals"]
        cmd += ["--goals", goals]
    except (OSError, ValueError, KeyError):
        pass
    return cmd + ([] if episodes is None else ["--episodes", str(episodes)])


def sweep(
    algos: Annotated[
        str, typer.Option("--algos", help="Methods, comma-separated (hydo train --algo values).")
    ],
    seeds: Annotated[str, typer.Option("--seeds", help="Seeds, comma-separated integers.")] = "0,1,2",
    out: Annotated[
        Path, typer.Option("--out", help="Sweep folder: one run folder per trial, <algo>-s<seed>.")
    ] = Path("runs/sweep"),
    config: Annotated[
        Path | None, typer.Option("--config", help="TOML file of config keys (hydo train).")
    ] = None,
    preset: Annotated[str | None, typer.Option("--preset", help="hydo train preset.")] = None,
    steps: Annotated[int | None, typer.Option("--steps", help="Env steps per trial.")] = None,
    minutes: Annotated[
        float | None, typer.Option("--minutes", help="Wall-clock budget per trial (0: none).")
    ] = None,
    goals: Annotated[Goals | None, typer.Option("--goals", help="Goal mode: planar or 6d.")] = None,
    objects: Annotated[
        str | None, typer.Option("--objects", help="Object set (hydo train --objects).")
    ] = None,
    clutter: Annotated[int | None, typer.Option("--clutter", help="Extra scene objects.")] = None,
    denoise_steps: Annotated[int | None, typer.Option("--k", help="Denoising steps K (ddpm / cm).")] = None,
    task: TaskOpt = None,
    workers: Annotated[int, typer.Option("--workers", help="hydo train --workers of each trial.")] = 1,
    threads: Annotated[int, typer.Option("--threads", help="torch threads per worker of each trial.")] = 1,
    jobs: Annotated[
        int | None,
        typer.Option(
            "--jobs", help="Local trials at a time (default: cores // (workers x threads)); not with --ray."
        ),
    ] = None,
    ray_address: Annotated[
        str | None,
        typer.Option(
            "--ray", help="Run on this Ray cluster (auto: the one `ray start` made here) via Ray Tune."
        ),
    ] = None,
    max_failures: Annotated[
        int, typer.Option("--max-failures", help="With --ray: retries of a failed trial (each resumes it).")
    ] = 3,
    compare_episodes: Annotated[
        int,
        typer.Option(
            "--compare-episodes",
            help="Run hydo eval --compare over the runs with this many episodes (0: print the command).",
        ),
    ] = 0,
) -> None:
    # 1. check everything before any trial starts
    algo_list = _csv("--algos", algos)
    known = list(ALGOS)
    bad = [a for a in algo_list if a not in known]
    if bad:
        raise HydoError(f"--algos: unknown method {bad[0]!r}; choose from {', '.join(known)}")
    try:
        seed_list = [int(s) for s in _csv("--seeds", seeds)]
    except ValueError:
        raise HydoError(f"--seeds {seeds}: give comma-separated integers, e.g. 0,1,2") from None
    if config is not None and preset is not None:
        raise HydoError("give --config or --preset, not both")
    if config is not None and not config.is_file():
        raise HydoError(f"--config {config}: no such file")
    if workers < 1 or threads < 1:
        raise HydoError("--workers and --threads must be at least 1")
    if jobs is not None and (jobs < 1 or ray_address is not None):
        raise HydoError("--jobs is a positive number of local trials at a time (not with --ray)")
    if steps is not None and steps < 1:
        raise HydoError(f"--steps must be at least 1, got {steps}")
    if minutes is not None and minutes < 0:
        raise HydoError(f"--minutes must be >= 0 (0: no budget), got {minutes}")
    if compare_episodes < 0:
        raise HydoError("--compare-episodes must be >= 0")
    if out.is_file():
        raise HydoError(f"--out {out} is a file, not a folder")
    values = {
        "--steps": steps, "--minutes": minutes, "--config": config, "--preset": preset,
        "--objects": objects, "--clutter": clutter, "--k": denoise_steps,
        "--goals": None if goals is None else goals.value, "--task": None if task is None else task.value,
    }  # fmt: skip
    assert set(values) == set(TRAIN_FLAGS)
    speed = ["--workers", str(workers), "--threads", str(threads)]
    train_args = [
        x
        for f, v in values.items()
        if v is not None
        for x in (f, str(Path(v).absolute()) if f == "--config" else str(v))
    ]
    resume_args = [x for f in RESUME_FLAGS if values[f] is not None for x in (f, str(values[f]))]
    out = out.absolute()  # trials (and Ray workers) may run elsewhere
    trials = [
        Trial(a, s, out / f"{a}-s{s}", out / "logs" / f"{a}-s{s}.log") for a in algo_list for s in seed_list
    ]
    spec = SweepSpec(out, trials, [*train_args, *speed], [*resume_args, *speed], workers * threads)
    out.mkdir(parents=True, exist_ok=True)
    spec.load_state()
    for t in trials:  # a folder holding something that is not a run would make hydo train refuse later
        if t.run.is_file():
            raise HydoError(f"{t.run} is a file; a sweep needs it for trial {t.name}")

    # 2. run what is not finished
    pending = spec.pending()
    done_before = len(trials) - len(pending)
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
    where = f"Ray cluster {ray_address}" if ray_address else f"{jobs or max(1, cores // spec.cpus)} at a time"
    console.print(
        f"hydo sweep: {len(trials)} trials ({len(algo_list)} methods x {len(seed_list)} seeds) in {out}; "
        f"{done_before} finished before, {len(pending)} to run, {where}, {spec.cpus} cores each"
    )
    if pending:
        if ray_address:
            results = run_ray(spec, ray_address, max_failures)
        else:
            results = run_local(spec, jobs or max(1, cores // spec.cpus))
        failed = [n for n, rc in results.items() if rc != 0]
        if failed:
            logs = ", ".join(str(out / "logs" / f"{n}.log") for n in failed)
            raise HydoError(
                f"{len(failed)} of {len(pending)} trials failed ({', '.join(failed)}): see {logs}; "
                "run the same command to resume them"
            )

    # 3. Table I over the runs
    if compare_episodes:
        cmd = eval_command(spec, compare_episodes)
        console.print(f"all {len(trials)} trials done; {shlex.join(cmd)}")
        rc = subprocess.call([sys.executable, "-m", "hydo_cli.main", *cmd[1:]])
        if rc != 0:
            raise typer.Exit(rc)
    else:
        console.print(
            f"all {len(trials)} trials done. Table I over them:\n  {shlex.join(eval_command(spec))}"
        )
