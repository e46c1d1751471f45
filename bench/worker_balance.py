"""How unevenly the training workers' env steps load the cores, and how much of it a deterministic
prediction could move.

Data-parallel training (``hydo_cli.trainer``, two workers on two cores) runs the workers in lock-step:
each steps its ``n_envs / 2`` envs, then every update's gradients are averaged, so at the first sync
of each iteration the worker whose pushes were cheaper waits for the other. This bench plays a
policy the way a training iteration does (one batched decision for all envs, then every env steps
once; env ``k`` belongs to worker ``k // (n_envs / 2)``) in one process and times every env
step. Per iteration it reports each worker's env time ``E_w`` and the spread ``max E − min E``: the
time the faster worker waits at that sync.

To move update rows from the slower worker to the faster one *deterministically* (the same run from
the same seed), the split must be fixed from numbers known before the pushes run, or from earlier
iterations. So the bench also fits, on its own data, how much of the spread each predictor explains
(least squares on every step, then summed per worker; the residual spread is what balancing on it
would leave: an optimistic bound, as the fit sees the data it is scored on):

- ``planned controls``: the push's length in physics steps (``sim.scene.push_controls``; 0 when the
  plan is refused), known once the action is chosen;
- ``object``: the mean step time of the env's object (fitted per object);
- ``object x planned controls``: the object's time per physics step times the planned length;
- ``previous iteration``: the spread of the iteration before (the same sign);
- ``object x physics steps (after)``: the object's time per physics step times the steps the push
  and settle really took: known only after the step, so no balance can use it; how much of the
  spread step counts could explain at best.

Usage::

    python bench/worker_balance.py --model models/hydo-cm-6d --seconds 150 --json runs/bench-balance.json

JSON: ``{"iterations", "env_step_ms", "env_step_std_ms", "worker_env_ms", "spread_ms",
"planned_controls": [mean, std], "physics_steps": [mean, std], "us_per_physics_step": {object: µs},
"predictors": {name: {"r2_per_step", "residual_spread_ms"}}, "meta"}``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections import defaultdict
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from hydo_cli.envs import make_envs  # noqa: E402
from hydo_cli.policies import load_policy  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402
from sim.primitive import SIM_WORKSPACE, PrimitiveRejected, check_plan, primitive_waypoints  # noqa: E402
from sim.scene import push_controls  # noqa: E402


def planned_controls(obs: dict, index: int, motion: np.ndarray, timestep: float) -> int:
    """Physics steps of the push the action asks for (approach to lift); 0 if the plan is refused."""
    waypoints = primitive_waypoints(obs["points"][index], obs["normals"][index], np.asarray(motion, float))
    try:
        check_plan(waypoints, SIM_WORKSPACE)
    except PrimitiveRejected:
        return 0
    return len(push_controls(waypoints, timestep))


def play(args: argparse.Namespace) -> dict[str, np.ndarray]:
    """Per (iteration, env): step time (s, the reset included when the episode ended), planned
    controls, physics steps taken, object name."""
    loaded = load_policy(args.model, seed=args.seed)
    contacts = args.contacts or loaded.contacts or "hydo"
    envs = make_envs(
        args.objects, args.goals, 0, "mesh", args.envs, loaded.n_obj, loaded.n_bg, contacts=contacts
    )
    rng = np.random.default_rng(args.seed)
    obs = [env.reset(seed=int(rng.integers(2**31)))[0] for env in envs]
    cols = defaultdict(list)
    t_end = time.perf_counter() + args.seconds
    while time.perf_counter() < t_end:
        actions = loaded.policy(obs)
        for k, (env, (index, motion)) in enumerate(zip(envs, actions, strict=True)):
            cols["controls"].append(planned_controls(obs[k], index, motion, env.scene.model.opt.timestep))
            cols["object"].append(env.scene.asset.name)
            t = time.perf_counter()
            obs[k], _, terminated, truncated, info = env.step((index, motion))
            if terminated or truncated:
                obs[k], _ = env.reset(seed=int(rng.integers(2**31)))
            cols["time"].append(time.perf_counter() - t)
            cols["physics"].append(info["physics_steps"])
    n = len(cols["time"]) // args.envs * args.envs  # whole iterations
    out = {k: np.asarray(v[:n]).reshape(-1, args.envs) for k, v in cols.items()}
    out["contacts"] = contacts
    return out


WORKERS = 2  # the trainer's default layout, one worker per core


def worker_sums(per_env: np.ndarray) -> np.ndarray:
    """``(iterations, envs)`` → ``(iterations, WORKERS)``: each worker's envs summed."""
    return per_env.reshape(len(per_env), WORKERS, -1).sum(-1)


def analyse(data: dict) -> dict:
    t, obj = data["time"], data["object"]
    mean_time = np.zeros_like(t)
    per_step = np.zeros_like(t)  # the object's seconds per physics step
    us_per_physics_step = {}
    for name in sorted(set(obj.ravel())):
        m = obj == name
        mean_time[m] = t[m].mean()
        per_step[m] = t[m].sum() / max(data["physics"][m].sum(), 1)
        us_per_physics_step[str(name)] = 1e6 * float(per_step[m][0])
    features = {
        "planned controls": data["controls"],
        "object": mean_time,
        "object x planned controls": per_step * data["controls"],
        "object x physics steps (after)": per_step * data["physics"],
    }
    per_worker = worker_sums(t)  # (iterations, 2)
    # the spread is |E_0 - E_1|; a split of the update rows on a prediction P leaves
    # |(E_0 - E_1) - (P_0 - P_1)|
    d = per_worker[:, 0] - per_worker[:, 1]
    result = {}
    for name, x in features.items():
        a = np.column_stack([x.ravel(), np.ones(x.size)])
        coef, *_ = np.linalg.lstsq(a, t.ravel(), rcond=None)
        pred = (a @ coef).reshape(t.shape)
        pw = worker_sums(pred)
        dp = pw[:, 0] - pw[:, 1]
        result[name] = {
            "r2_per_step": float(1 - ((t - pred) ** 2).mean() / t.var()),
            "residual_spread_ms": 1e3 * float(np.abs(d - dp).mean()),
        }
    result["previous iteration"] = {
        "r2_per_step": None,
        "residual_spread_ms": 1e3 * float(np.abs(d[1:] - d[:-1]).mean()),
        "lag1_correlation": float(np.corrcoef(d[1:], d[:-1])[0, 1]),
    }
    return {
        "iterations": len(t),
        "env_step_ms": 1e3 * float(t.mean()),
        "env_step_std_ms": 1e3 * float(t.std()),
        "worker_env_ms": 1e3 * float(per_worker.mean()),
        "spread_ms": 1e3 * float(np.abs(d).mean()),
        "planned_controls": [float(data["controls"].mean()), float(data["controls"].std())],
        "physics_steps": [float(data["physics"].mean()), float(data["physics"].std())],
        # an env step's time per physics step (observation and reward included), by object
        "us_per_physics_step": dict(sorted(us_per_physics_step.items(), key=lambda kv: kv[1])),
        "predictors": result,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default=str(ROOT / "models" / "hydo-cm-6d"), help="as hydo eval")
    ap.add_argument("--goals", default="6d", choices=["planar", "6d"])
    ap.add_argument("--objects", default="train-wide", help="the object set (configs/6d-train.toml's)")
    ap.add_argument("--contacts", choices=["hydo", "hacman"], help="default: the model's own")
    ap.add_argument("--envs", type=int, default=8, help="n_envs of the training config")
    ap.add_argument("--seconds", type=float, default=150.0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    if args.envs < WORKERS or args.envs % WORKERS:
        raise SystemExit(f"bench/worker_balance.py: --envs must be a positive multiple of {WORKERS}")
    data = play(args)
    if len(data["time"]) < 3:
        raise SystemExit("bench/worker_balance.py: fewer than 3 iterations; raise --seconds")
    results = analyse(data)
    results["meta"] = {
        **{k: getattr(args, k) for k in ("model", "goals", "objects", "envs", "seconds", "seed")},
        "workers": WORKERS,
        "contacts": data["contacts"],
        "cpus": os.cpu_count(),
        "platform": platform.platform(),
    }

    from rich.console import Console
    from rich.table import Table

    Console().print(
        f"{results['iterations']} iterations of {args.envs} envs over {WORKERS} workers: env step "
        f"{results['env_step_ms']:.1f} ± {results['env_step_std_ms']:.1f} ms, per worker and iteration "
        f"{results['worker_env_ms']:.1f} ms, spread (the wait at the first sync) {results['spread_ms']:.1f} ms"
    )
    cost = list(results["us_per_physics_step"].items())
    Console().print(
        "physics steps per env step: planned {:.0f} ± {:.0f}, taken {:.0f} ± {:.0f}; µs per physics "
        "step, cheapest {}, dearest {}".format(
            *results["planned_controls"],
            *results["physics_steps"],
            ", ".join(f"{k} {v:.0f}" for k, v in cost[:3]),
            ", ".join(f"{k} {v:.0f}" for k, v in cost[-3:]),
        )
    )
    table = Table(title="what a deterministic split of the update rows could balance")
    for col in ("predictor", "R² per step", "spread left, ms"):
        table.add_column(col, justify="right")
    for name, r in results["predictors"].items():
        r2 = "" if r["r2_per_step"] is None else f"{r['r2_per_step']:.3f}"
        table.add_row(name, r2, f"{r['residual_spread_ms']:.1f}")
    Console().print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
