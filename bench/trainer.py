"""Env steps, gradient updates and sample-gradients per hour of the real training loop.

Runs ``hydo train`` for ``--seconds`` each, on the default config (6D goals unless told otherwise):

* **default**: as a user runs it (``--workers 2``: both cores, data-parallel, ``hydo_cli.trainer``);
* **serial**: the same loop confined to one core (``--workers 1 --threads 1``, the process pinned to
  CPU 0 with ``sched_setaffinity``), env steps and updates interleaved;
* with ``--baseline REV``: **baseline**, the default layout of another commit's code (checked out
  into a temporary ``git worktree``), alternated with *default* ``--repeats`` times in the same
  session, so that the two are compared on the same machine at the same moment (machines of this
  class differ by ~1.8× in absolute speed). The serial layout is then left out.

A *sample-gradient* is one transition's contribution to one critic update: updates × the run's
``batch_size`` (summed over the workers).

Rates are read from each run's ``metrics.jsonl`` between the first row with updates (learning has
started) and the last one, so start-up and the random-action warm-up are not counted. Evaluation is
off (``eval_every = 0``) so that both runs spend their time on the loop alone. Prints a table;
``--json FILE`` writes ``{"default": {...}, "serial": {...}, "env_steps_speedup", "updates_speedup",
"meta"}`` where each run has ``env_steps_per_hour``, ``updates_per_hour`` and
``updates_per_env_step`` (the update-to-data ratio, a setting: equal in both) and ``sync_wait_share``
(the mean share of the window the workers sat at the gradient syncs and exchanges, the lock-step's
idle time, from ``metrics.jsonl``; None for one worker or for code that does not log it).

``--config FILE`` takes this tree's layouts' settings from a training config, as ``hydo train --config
FILE`` would: every key but the ones the bench sets itself (run length, evaluation, checkpoints,
logging, and the goal mode and object set, which stay ``--goals`` / ``--objects`` so that a baseline
commit that lacks the config's object set still runs the same ones). The baseline keeps its own
defaults: that is "the current main's loop".

Run it on an otherwise idle machine::

    python bench/trainer.py --seconds 180 --json out/trainer.json
    python bench/trainer.py --goals planar --seconds 120
    python bench/trainer.py --baseline a4909d9 --config configs/6d-train.toml --seconds 100
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from sim.atomic import atomic_write_text  # noqa: E402

sys.path.append(str(ROOT / "bench"))  # after the repo root: bench/sim.py must not shadow sim
from _baseline import checkout, remove_checkout  # noqa: E402

LAYOUTS = {
    "default": ["--workers", "2"],
    "serial": ["--workers", "1", "--threads", "1"],
    "baseline": ["--workers", "2"],
}
RATES = ("env_steps_per_hour", "updates_per_hour", "sample_gradients_per_hour")


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int | float):
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)  # a TOML basic string for the plain names configs hold
    raise SystemExit(f"bench/trainer.py: cannot pass on a setting of type {type(v).__name__}")


def parse_toml(text: str, where: str) -> dict:
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise SystemExit(f"bench/trainer.py: {where} is not valid TOML: {e}") from None


def merge(*layers: dict) -> dict:
    """Later layers win, key by key, tables (``[agent]``) merged key by key too."""
    out: dict = {}
    for layer in layers:
        for k, v in layer.items():
            out[k] = {**out.get(k, {}), **v} if isinstance(v, dict) else v
    return out


def toml_text(values: dict) -> str:
    """Flat keys first, then each table: the layout ``hydo train --config`` reads."""
    lines = [f"{k} = {_toml_value(v)}" for k, v in values.items() if not isinstance(v, dict)]
    for name, table in values.items():
        if isinstance(table, dict):
            lines += [f"[{name}]", *(f"{k} = {_toml_value(v)}" for k, v in table.items())]
    return "".join(f"{line}\n" for line in lines)


def bench_settings(args: argparse.Namespace) -> dict:
    """What the bench sets in every run, whatever --config says: run length, no evaluation, no
    checkpoints, its log interval, and the goal mode and object set of its flags."""
    return {
        "goals": args.goals,
        "objects": args.objects,
        "steps": 1_000_000_000,
        "max_minutes": args.seconds / 60,
        "eval_every": 0,
        "eval_episodes": 1,
        "checkpoint_every": 1_000_000_000,
        "log_every": args.log_every,
    }


def config_settings(path: Path, args: argparse.Namespace) -> dict:
    """A training config's settings but the bench's own: what ``hydo train --config PATH`` changes."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as e:
        raise SystemExit(f"bench/trainer.py: --config {path} cannot be read ({type(e).__name__})") from None
    ours = bench_settings(args)
    return {k: v for k, v in parse_toml(text, f"--config {path}").items() if k not in ours}


def run_loop(name: str, args: argparse.Namespace, folder: Path, src: Path = ROOT, tag: str = "") -> dict:
    """One ``hydo train`` of ``args.seconds`` with the code in ``src``; steady-state rates from
    ``metrics.jsonl``."""
    name_tag = f"{name}{tag}"
    toml = folder / f"{name_tag}.toml"
    layers = [bench_settings(args), args.config_settings if name != "baseline" else {}, args.set_settings]
    if name == "default":
        layers.append(args.set_default_settings)
    toml.write_text(toml_text(merge(*layers)))
    run = folder / name_tag
    cmd = [sys.executable, "-m", "hydo_cli.main", "train", "--config", str(toml), "--out", str(run)]
    cmd += LAYOUTS[name]
    pin = (
        (lambda: os.sched_setaffinity(0, {0}))
        if name == "serial" and hasattr(os, "sched_setaffinity")
        else None
    )
    t0 = time.perf_counter()
    env = {**os.environ, "PYTHONPATH": str(src)}  # src's packages win over any installed copy
    r = subprocess.run(cmd, cwd=src, capture_output=True, text=True, preexec_fn=pin, env=env)
    if r.returncode != 0:
        raise SystemExit(f"bench/trainer.py: {name} run failed:\n{r.stderr[-2000:]}")
    rows = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()]
    learning = [row for row in rows if row["updates"] > 0]
    if len(learning) < 2:
        raise SystemExit(
            f"bench/trainer.py: {name}: fewer than 2 log rows after learning started; raise --seconds"
        )
    a, b = learning[0], learning[-1]
    dt = b["wall_s"] - a["wall_s"]
    steps, updates = b["env_steps"] - a["env_steps"], b["updates"] - a["updates"]
    batch_size = json.loads((run / "config.json").read_text())["batch_size"]
    # the workers' idle share in the lock-step (rows of code that logs it, with more than one worker)
    waits = [row["sync_wait_share"] for row in learning[1:] if row.get("sync_wait_share") is not None]
    return {
        "command": " ".join(cmd[2:]),
        "window_s": dt,
        "env_steps": steps,
        "updates": updates,
        "env_steps_per_hour": steps / dt * 3600,
        "updates_per_hour": updates / dt * 3600,
        "batch_size": batch_size,
        "sample_gradients_per_hour": updates * batch_size / dt * 3600,
        "updates_per_env_step": updates / steps,
        "sync_wait_share": statistics.mean(waits) if waits else None,
        "total_wall_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=180.0, help="wall-clock budget of each run")
    ap.add_argument("--goals", default="6d", help="goal mode of the runs (default: the 6D task)")
    ap.add_argument("--objects", default="train", help="object set of the runs")
    ap.add_argument("--log-every", type=int, default=200, help="env steps between metric rows")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="extra TOML line")
    ap.add_argument(
        "--set-default",
        action="append",
        default=[],
        metavar="LINE",
        help="extra TOML line for the default layout only (with --baseline: a setting to weigh against it)",
    )
    ap.add_argument(
        "--baseline",
        metavar="REV",
        help="compare the default layout against this commit's code (a git revision) instead of serial",
    )
    ap.add_argument(
        "--config",
        type=Path,
        help="take this tree's settings (not the baseline's) from a training config, e.g. configs/6d-train.toml",
    )
    ap.add_argument("--repeats", type=int, default=1, help="with --baseline: alternations of the two")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit("bench/trainer.py: --repeats must be at least 1")
    args.config_settings = config_settings(args.config, args) if args.config else {}
    args.set_settings = parse_toml("\n".join(args.set), "--set")
    args.set_default_settings = parse_toml("\n".join(args.set_default), "--set-default")

    results: dict = {}
    with tempfile.TemporaryDirectory(prefix="hydo-bench-trainer-") as tmp:
        if args.baseline:
            src = checkout(args.baseline, Path(tmp))
            try:
                runs: dict[str, list[dict]] = {"baseline": [], "default": []}
                for k in range(args.repeats):  # alternate, so slow spells of a shared machine hit both
                    runs["baseline"].append(run_loop("baseline", args, Path(tmp), src, tag=f"-{k}"))
                    runs["default"].append(run_loop("default", args, Path(tmp), tag=f"-{k}"))
            finally:
                remove_checkout(src)
            for name, rs in runs.items():
                waits = [r["sync_wait_share"] for r in rs if r["sync_wait_share"] is not None]
                results[name] = {
                    **rs[0],
                    **{key: statistics.median(r[key] for r in rs) for key in RATES},
                    "sync_wait_share": statistics.median(waits) if waits else None,
                    "window_s": sum(r["window_s"] for r in rs),
                }
            results["runs"] = runs
            names, ref = ("baseline", "default"), "baseline"
        else:
            for name in ("default", "serial"):
                results[name] = run_loop(name, args, Path(tmp))
            names, ref = ("default", "serial"), "serial"
    d, s = results["default"], results[ref]
    results["env_steps_speedup"] = d["env_steps_per_hour"] / s["env_steps_per_hour"]
    results["updates_speedup"] = d["updates_per_hour"] / s["updates_per_hour"]
    results["sample_gradients_speedup"] = d["sample_gradients_per_hour"] / s["sample_gradients_per_hour"]
    results["meta"] = {
        "seconds": args.seconds,
        "goals": args.goals,
        "objects": args.objects,
        "set": args.set,
        "set_default": args.set_default,
        "config": str(args.config) if args.config else None,
        "config_settings": args.config_settings,
        "baseline": args.baseline,
        "repeats": args.repeats if args.baseline else 1,
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
    }

    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"training loop, {args.goals} goals, {args.seconds:.0f} s per run")
    cols = (
        "layout",
        "env steps/h",
        "updates/h",
        "sample-gradients/h",
        "updates/env step",
        "sync wait",
        "window s",
    )
    for col in cols:
        table.add_column(col, justify="right")
    for name in names:
        r = results[name]
        table.add_row(
            name + (f" ({args.baseline})" if name == "baseline" else ""),
            f"{r['env_steps_per_hour']:,.0f}",
            f"{r['updates_per_hour']:,.0f}",
            f"{r['sample_gradients_per_hour']:,.0f}",
            f"{r['updates_per_env_step']:.3f}",
            "-" if r["sync_wait_share"] is None else f"{r['sync_wait_share']:.1%}",
            f"{r['window_s']:.0f}",
        )
    table.add_row(
        "speedup",
        f"{results['env_steps_speedup']:.2f}×",
        f"{results['updates_speedup']:.2f}×",
        f"{results['sample_gradients_speedup']:.2f}×",
        "",
        "",
        "",
    )
    Console().print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
