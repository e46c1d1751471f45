"""Gradient updates per second of every algorithm at the default point counts.

Builds each agent from ``AgentConfig`` defaults (plus any overrides), fills a replay buffer with
random observations, and times ``agent.update`` on sampled batches (sampling excluded; it is
measured separately as ``sample_ms``). Prints a table; ``--json FILE`` writes
``{"<algo>": {"updates_per_s", "batch_size", "params", ...}, "meta": {...}}``.

Examples::

    python bench/learner.py
    python bench/learner.py --algos hydo-cm --batch-sizes 32,64,128 --json out/learner.json
    python bench/learner.py --algos hydo --set actor_points=32
    python bench/learner.py --algos hydo-cm --threads 1 --baseline 07e6d1a --repeats 3

With ``--baseline REV`` the same measurement runs on REV's code (``bench/_baseline.py``: a temporary
git worktree) and on this tree's, alternately ``--repeats`` times in subprocesses, and the table
gives each side's median updates/s and their ratio (JSON: ``{"baseline": {...}, "current": {...},
"runs": [...], "speedup": {key: ratio}, "meta"}``).
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
from dataclasses import fields
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from models.algos import ALGOS, AgentConfig, HybridAgent  # noqa: E402
from models.perf import configure_cpu, native_bf16, update_autocast  # noqa: E402
from models.replay import ReplayBuffer, Transition  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402

sys.path.append(str(Path(__file__).resolve().parent))  # after the repo root: bench/sim.py must not shadow sim
from _baseline import checkout, remove_checkout  # noqa: E402


def parse_overrides(items: list[str]) -> dict:
    """``["key=value", ...]`` → typed AgentConfig overrides."""
    types = {f.name: f.type for f in fields(AgentConfig)}
    out = {}
    for item in items:
        key, _, raw = item.partition("=")
        if key not in types:
            raise SystemExit(f"--set: unknown AgentConfig field {key!r}")
        t = str(types[key])
        if raw.lower() == "none":
            out[key] = None
        elif "bool" in t:
            out[key] = raw.lower() in ("1", "true", "yes")
        elif "int" in t:
            out[key] = int(raw)
        elif "float" in t:
            out[key] = float(raw)
        else:
            out[key] = raw
    return out


def fill_buffer(buf: ReplayBuffer, n: int, rng: np.random.Generator) -> None:
    """Random but contract-shaped transitions: object cloud near the bin centre, flows of a few cm."""
    npts = buf.n_points
    for _ in range(n):
        pts = rng.uniform(-0.2, 0.2, size=(2, npts, 3)).astype(np.float32)
        pts[:, : buf.n_obj] *= 0.25
        feats = np.zeros((2, npts, 4), dtype=np.float32)
        feats[:, : buf.n_obj, 0] = 1.0
        feats[:, : buf.n_obj, 1:] = rng.normal(0, 0.05, size=(2, buf.n_obj, 3))
        buf.add(
            Transition(
                points=pts[0],
                features=feats[0],
                index=int(rng.integers(buf.n_obj)),
                motion=rng.uniform(-1, 1, 3),
                reward=-float(rng.uniform(0, 0.2)),
                next_points=pts[1],
                next_features=feats[1],
                terminated=bool(rng.random() < 0.1),
                truncated=bool(rng.random() < 0.1),
            )
        )


def time_updates(agent: HybridAgent, buf: ReplayBuffer, batch_size: int, seconds: float, bf16: bool):
    """Updates/s of ``agent.update`` over fresh batches, sampling excluded.

    The budget is split into 1-s windows; the best window is the headline (like ``timeit``'s
    minimum: other work on a shared machine only ever slows a window down) and the median window is
    recorded beside it. Returns ``(best, median, sample_ms)``.
    """
    ctx = update_autocast("bf16" if bf16 else "fp32")  # the trainer's own context
    batches = [buf.sample(batch_size) for _ in range(16)]
    rates = []
    with ctx:
        for i in range(3):  # warm-up: allocator, autograd caches
            agent.update(batches[i])
        spent, n_total = 0.0, 0
        while spent < seconds or len(rates) < 3:
            n, t0 = 0, time.perf_counter()
            while True:
                agent.update(batches[(n_total + n) % len(batches)])
                n += 1
                dt = time.perf_counter() - t0
                if dt >= min(1.0, seconds) and n >= 3:
                    break
            rates.append(n / dt)
            spent += dt
            n_total += n
    t1 = time.perf_counter()
    for _ in range(20):
        buf.sample(batch_size)
    sample_ms = (time.perf_counter() - t1) / 20 * 1e3
    return max(rates), statistics.median(rates), sample_ms


def compile_agent(agent: HybridAgent, buf: ReplayBuffer, batch_size: int) -> float:
    """``torch.compile`` every network the update runs (the optimisers keep the same parameters);
    returns the seconds the first updates took (compilation, for each policy-delay branch)."""
    methods = {
        "encoder": ("encode_context", "head", "forward"),
        "encoder_target": ("forward",),
        "critic": ("forward", "q1"),
        "critic_target": ("forward",),
        "motion_policy": ("sample",),
    }
    for name, names in methods.items():
        module = getattr(agent, name)
        for method in names:
            setattr(module, method, torch.compile(getattr(module, method), dynamic=False))
    t0 = time.perf_counter()
    for _ in range(4):
        agent.update(buf.sample(batch_size))
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--algos", default=",".join(ALGOS), help="comma-separated --algo values")
    ap.add_argument("--batch-sizes", default="32", help="comma-separated batch sizes")
    ap.add_argument("--seconds", type=float, default=5.0, help="timing budget per (algo, batch size)")
    ap.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    ap.add_argument("--bf16", action="store_true", help="run updates under bf16 autocast")
    ap.add_argument(
        "--compile",
        action="store_true",
        help="wrap the encoder, critic and motion policy (online and target) in torch.compile; the "
        "first updates (compilation) are excluded from the timing and reported as compile_s",
    )
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="AgentConfig override")
    ap.add_argument("--json", type=Path, help="write results to this JSON file")
    ap.add_argument("--baseline", metavar="REV", help="compare against this commit's code (a git revision)")
    ap.add_argument("--repeats", type=int, default=3, help="with --baseline: alternations of the two")
    args = ap.parse_args(argv)
    if args.baseline:
        return compare_with_baseline(args, argv if argv is not None else sys.argv[1:])

    cpu = configure_cpu(args.threads)
    if args.bf16 and native_bf16() is None:
        print(
            "note: this CPU has no native bf16 (no amx_bf16 / avx512_bf16): autocast emulates it", flush=True
        )
    overrides = parse_overrides(args.set)
    batch_sizes = [int(x) for x in args.batch_sizes.split(",")]
    results: dict = {}
    rows = []
    for algo in args.algos.split(","):
        cfg = AgentConfig(algo=algo, **overrides)
        agent = HybridAgent(cfg)
        buf = ReplayBuffer(2000, cfg.n_obj, cfg.n_bg, seed=0)
        fill_buffer(buf, 256, np.random.default_rng(0))
        compile_s = None
        if args.compile:
            compile_s = compile_agent(agent, buf, batch_sizes[0])
        for bs in batch_sizes:
            ups, ups_median, sample_ms = time_updates(agent, buf, bs, args.seconds, args.bf16)
            key = algo if len(batch_sizes) == 1 else f"{algo}@{bs}"
            results[key] = {
                "algo": algo,
                "updates_per_s": round(ups, 2),
                "updates_per_s_median": round(ups_median, 2),
                "batch_size": bs,
                "samples_per_s": round(ups * bs, 1),
                "params": agent.num_parameters(),
                "sample_ms": round(sample_ms, 3),
                "n_obj": cfg.n_obj,
                "n_bg": cfg.n_bg,
                "compile_s": compile_s,
            }
            rows.append(results[key])
            print(
                f"{algo:12s} B={bs:4d} {ups:7.1f} upd/s (median {ups_median:5.1f}) {ups * bs:8.0f} samples/s "
                f"params={agent.num_parameters():7d} sample={sample_ms:.2f} ms",
                flush=True,
            )
    results["meta"] = {
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "malloc_retain": cpu["malloc_retain"],
        "bf16": args.bf16,
        "compile": args.compile,
        "overrides": overrides,
        "machine": platform.processor() or platform.machine(),
        "cpu_capability": torch.backends.cpu.get_cpu_capability(),
        "native_bf16": native_bf16(),
        "python": platform.python_version(),
    }
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(
            title=f"learner updates/s (torch {torch.__version__}, {torch.get_num_threads()} threads)"
        )
        for col in ("algo", "batch", "updates/s", "median", "samples/s", "params", "sample ms"):
            table.add_column(col, justify="right" if col != "algo" else "left")
        for r in rows:
            table.add_row(
                r["algo"],
                str(r["batch_size"]),
                f"{r['updates_per_s']:.1f}",
                f"{r['updates_per_s_median']:.1f}",
                f"{r['samples_per_s']:.0f}",
                str(r["params"]),
                f"{r['sample_ms']:.2f}",
            )
        Console().print(table)
    except ImportError:
        pass
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2) + "\n")
    return 0


def _strip_baseline(argv: list[str]) -> list[str]:
    """``argv`` without ``--baseline``, ``--repeats`` and ``--json`` (and their values)."""
    out, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        name = a.split("=", 1)[0]
        if name in ("--baseline", "--repeats", "--json"):
            skip = "=" not in a
            continue
        out.append(a)
    return out


def compare_with_baseline(args: argparse.Namespace, argv: list[str]) -> int:
    """REV's ``bench/learner.py`` and this one, alternately in subprocesses with the same arguments;
    median updates/s of each (algo, batch size) and the ratio current / baseline."""
    if args.repeats < 1:
        raise SystemExit("bench/learner.py: --repeats must be at least 1")
    here = Path(__file__).resolve().parents[1]
    common = _strip_baseline(argv)
    runs: list[dict] = []
    with tempfile.TemporaryDirectory(prefix="hydo-bench-learner-") as tmp:
        src = checkout(args.baseline, Path(tmp))
        try:
            for k in range(args.repeats):  # alternate, so slow spells of a shared machine hit both
                for side, root in (("baseline", src), ("current", here)):
                    out = Path(tmp) / f"{side}-{k}.json"
                    cmd = [sys.executable, str(root / "bench" / "learner.py"), *common, "--json", str(out)]
                    r = subprocess.run(cmd, cwd=root, capture_output=True, text=True)
                    if r.returncode != 0:
                        raise SystemExit(f"bench/learner.py: the {side} run failed:\n{r.stderr[-2000:]}")
                    runs.append({"side": side, "repeat": k, "results": json.loads(out.read_text())})
        finally:
            remove_checkout(src)
    keys = [key for key in runs[0]["results"] if key != "meta"]
    results: dict = {"runs": runs, "speedup": {}}
    for side in ("baseline", "current"):
        results[side] = {
            key: statistics.median(r["results"][key]["updates_per_s"] for r in runs if r["side"] == side)
            for key in keys
        }
    for key in keys:
        results["speedup"][key] = results["current"][key] / results["baseline"][key]
    results["meta"] = {
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "baseline": args.baseline,
        "repeats": args.repeats,
        "machine": platform.processor() or platform.machine(),
        "native_bf16": native_bf16(),
    }
    for key in keys:
        print(
            f"{key:16s} baseline {results['baseline'][key]:7.1f} upd/s  current {results['current'][key]:7.1f} "
            f"upd/s  {results['speedup'][key]:.2f}x  (medians of {args.repeats})",
            flush=True,
        )
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
