"""Simulator throughput: env steps, observations, primitives and raw physics on one core.

Usage::

    python bench/sim.py                       # prints a table (~30-45 s)
    python bench/sim.py --json runs/bench-sim.json --seconds 10
    python bench/sim.py --goals 6d            # env steps on 6D goals (flips: other contacts, settles)

Figures (JSON keys; all single-process, ``OPENBLAS_NUM_THREADS=1``):

- ``mesh_steps_per_s``: ``hydo/Bin-v0`` env steps per second with mesh observations, a random policy,
  ``train`` objects and ``--goals`` (default ``planar``, which the earlier figures used); reset
  time excluded and reported as ``reset_ms``.
- ``obs_mesh_ms``: one mesh observation (segmented clouds + the fixed-size observation).
- ``render_ms_per_step``: one rendered observation (three 240x320 depth cameras, background
  subtraction, back-projection, normals) once the object's renderer exists; ``render_first_ms`` is
  the first observation of a new object (renderer + background render).
- ``primitive_ms``: executing one accepted primitive (push + settle), ``primitive_physics_steps``
  its mean physics steps.
- ``physics_steps_per_s``: raw ``mujoco.mj_step`` rate of the scene with an object resting in the bin.
- ``refused_fraction``: fraction of uniformly random pushes (random point and motion, ``train``
  objects) the simulator refuses; ``refusals_predicted``: the fraction of those refusals that
  ``sim.primitive`` predicts from the observation (workspace gate + ``start_clear``);
  ``false_refusals``: pushes it predicts refused that the simulator runs (should be 0).
- ``feasible_points_ms``: ``sim.primitive.feasible_points`` for one training decision (8 envs x
  128 object points, 256-point clouds), the location policy's per-step cost.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

# One core, EGL before mujoco's first import; the repo root (not bench/, whose sim.py is this file)
# must come first on the path so `import sim` finds the package.
os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
os.environ.setdefault("MUJOCO_GL", "egl")
ROOT = Path(__file__).resolve().parent.parent
sys.path[:] = [str(ROOT)] + [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]

import gymnasium  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import sim.env  # noqa: E402, F401  (registers hydo/Bin-v0)
from sim.atomic import atomic_write_text  # noqa: E402
from sim.contract import CONTACT_MODELS, GOAL_MODES  # noqa: E402
from sim.primitive import SIM_WORKSPACE, PrimitiveRejected, check_plan, primitive_waypoints  # noqa: E402


def bench_env_steps(seconds: float, seed: int, goals: str = "planar", contacts: str = "hydo") -> dict:
    """Random-policy env steps (mesh observations, ``goals`` mode, ``contacts`` model) for ``seconds``
    of stepping time."""
    env = gymnasium.make("hydo/Bin-v0", objects="train", goals=goals, obs="mesh", contacts=contacts)
    env.action_space.seed(seed)
    env.reset(seed=seed)  # builds the first scene; not timed
    steps, step_s, resets, reset_s = 0, 0.0, 0, 0.0
    t_obs = []
    u = env.unwrapped
    done = True
    while step_s < seconds:
        if done:
            t = time.perf_counter()
            env.reset()
            reset_s += time.perf_counter() - t
            resets += 1
            t = time.perf_counter()
            u._observe()
            t_obs.append(time.perf_counter() - t)
        action = env.action_space.sample()
        t = time.perf_counter()
        _, _, terminated, truncated, _ = env.step(action)
        step_s += time.perf_counter() - t
        steps += 1
        done = terminated or truncated
    env.close()
    return {
        "mesh_steps_per_s": steps / step_s,
        "mesh_steps": steps,
        "reset_ms": 1e3 * reset_s / resets,
        "obs_mesh_ms": 1e3 * float(np.median(t_obs)),
    }


def bench_primitives(n: int, seed: int) -> dict:
    """Mean wall time of executing ``n`` accepted random primitives (push + settle)."""
    env = gymnasium.make("hydo/Bin-v0", objects="train", goals="planar", obs="mesh")
    u = env.unwrapped
    rng = np.random.default_rng(seed)
    times, phys = [], []
    obs, _ = env.reset(seed=seed)
    while len(times) < n:
        i = int(rng.integers(u.n_obj))
        waypoints = primitive_waypoints(obs["points"][i], obs["normals"][i], rng.uniform(-1, 1, 3))
        try:
            check_plan(waypoints, SIM_WORKSPACE)
        except PrimitiveRejected:
            continue
        t = time.perf_counter()
        result = u.scene.execute_primitive(waypoints)
        dt = time.perf_counter() - t
        if result.executed:
            times.append(dt)
            phys.append(result.physics_steps)
        obs, _ = env.reset()
    env.close()
    return {"primitive_ms": 1e3 * float(np.mean(times)), "primitive_physics_steps": float(np.mean(phys))}


def bench_render(n_objects: int, per_object: int, seed: int) -> dict:
    """Rendered observations on ``n_objects`` train objects, ``per_object`` each after the first."""
    env = gymnasium.make("hydo/Bin-v0", objects="train", goals="planar", obs="render")
    u = env.unwrapped
    names = [a.name for a in u.assets]
    rest = []
    for k in range(n_objects):
        # reset() already made the object's renderer and background (its first observation)
        env.reset(seed=seed + k, options={"object": names[(k * 7) % len(names)]})
        for _ in range(per_object):
            t = time.perf_counter()
            u._observe()
            rest.append(time.perf_counter() - t)
    # Cost of a new object's first observation: a fresh observer (new renderer + background).
    from sim.render import RenderObserver

    fresh = RenderObserver()
    t = time.perf_counter()
    fresh.segmented_clouds(u.scene)
    first_ms = 1e3 * (time.perf_counter() - t)
    fresh.close()
    u.observer.close()
    env.close()
    return {
        "render_ms_per_step": 1e3 * float(np.median(rest)),
        "render_ms_p90": 1e3 * float(np.percentile(rest, 90)),
        "render_first_ms": first_ms,
    }


def bench_physics(seconds: float, seed: int) -> dict:
    """Raw mj_step rate with a train object resting in the bin (hand parked)."""
    env = gymnasium.make("hydo/Bin-v0", objects="train", goals="planar", obs="mesh")
    env.reset(seed=seed)
    scene = env.unwrapped.scene
    m, d = scene.model, scene.data
    mujoco.mj_step(m, d, nstep=200)  # settle any residual motion
    n, t0 = 0, time.perf_counter()
    while time.perf_counter() - t0 < seconds:
        mujoco.mj_step(m, d, nstep=500)
        n += 500
    rate = n / (time.perf_counter() - t0)
    env.close()
    return {"physics_steps_per_s": rate, "physics_timestep_s": float(m.opt.timestep)}


def bench_feasibility(episodes: int, seed: int) -> dict:
    from sim.env import BinEnv
    from sim.primitive import feasible_points, plans_inside, primitive_waypoints, start_clear

    env = BinEnv("train", "planar")
    rng = np.random.default_rng(seed)
    pushes = refused = caught = false_refusals = 0
    for ep in range(episodes):
        obs, _ = env.reset(seed=seed + ep)
        for _ in range(5):
            i, motion = int(rng.integers(env.n_obj)), rng.uniform(-1, 1, 3).astype(np.float32)
            w = primitive_waypoints(obs["points"][i], obs["normals"][i], motion)
            predicted_ok = bool(plans_inside(w) & start_clear(w[None, None, 0], obs["points"][None])[0, 0])
            obs, _, term, trunc, info = env.step((i, motion))
            pushes += 1
            refused += info["rejected"]
            caught += info["rejected"] and not predicted_ok
            false_refusals += (not info["rejected"]) and not predicted_ok
            if term or trunc:
                break
    b = 8
    pts = np.repeat(obs["points"][None], b, 0)
    nrm, mot = np.repeat(obs["normals"][None], b, 0), rng.uniform(-1, 1, (b, env.n_obj, 3))
    t = time.perf_counter()
    for _ in range(50):
        feasible_points(pts[:, : env.n_obj], nrm, mot, pts)
    return {
        "random_pushes": pushes,
        "refused_fraction": refused / pushes,
        "refusals_predicted": caught / max(refused, 1),
        "false_refusals": false_refusals,
        "feasible_points_ms": (time.perf_counter() - t) / 50 * 1e3,
    }


def write_json_atomic(path: Path, obj: dict) -> None:
    atomic_write_text(path, json.dumps(obj, indent=2) + "\n")


def print_table(results: dict) -> None:
    goals = results.get("meta", {}).get("goals", "planar")
    rows = [
        ("mesh_steps_per_s", f"env steps/s (mesh obs, random policy, train, {goals})", "{:.1f}"),
        ("reset_ms", "reset (ms)", "{:.2f}"),
        ("obs_mesh_ms", "mesh observation (ms)", "{:.3f}"),
        ("render_ms_per_step", "rendered observation, 3 cameras (ms, median)", "{:.1f}"),
        ("render_ms_p90", "rendered observation (ms, p90)", "{:.1f}"),
        ("render_first_ms", "first rendered observation of a model (ms)", "{:.0f}"),
        ("primitive_ms", "one primitive: push + settle (ms)", "{:.2f}"),
        ("primitive_physics_steps", "physics steps per primitive", "{:.0f}"),
        ("physics_steps_per_s", "raw mj_step/s (object resting)", "{:.0f}"),
        ("refused_fraction", "random pushes the simulator refuses", "{:.1%}"),
        ("refusals_predicted", "of those, predicted from the observation", "{:.1%}"),
        ("false_refusals", "predicted refused but run by the simulator", "{:d}"),
        ("feasible_points_ms", "feasible_points, 8 envs x 128 points (ms)", "{:.2f}"),
    ]
    try:
        from rich.console import Console
        from rich.table import Table

        table = Table(title="bench/sim.py (one core)")
        table.add_column("key")
        table.add_column("measure")
        table.add_column("value", justify="right")
        for key, label, fmt in rows:
            table.add_row(key, label, fmt.format(results[key]))
        Console().print(table)
    except ImportError:
        for key, label, fmt in rows:
            print(f"{key:24s} {label:50s} {fmt.format(results[key]):>10s}")


def main(argv: list[str] | None = None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", type=Path, default=None, help="write the figures to this JSON file")
    parser.add_argument("--seconds", type=float, default=10.0, help="env stepping time for mesh_steps_per_s")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--goals", choices=GOAL_MODES, default="planar", help="goal mode of the env-steps figure"
    )
    parser.add_argument(
        "--contacts", choices=CONTACT_MODELS, default="hydo", help="contact model of the env-steps figure"
    )
    args = parser.parse_args(argv)
    if args.seconds <= 0:
        parser.error(f"--seconds must be > 0. Got {args.seconds}.")

    t0 = time.perf_counter()
    results: dict = {}
    results.update(bench_env_steps(args.seconds, args.seed, args.goals, args.contacts))
    results.update(bench_primitives(n=30, seed=args.seed))
    results.update(bench_physics(seconds=min(3.0, args.seconds), seed=args.seed))
    results.update(bench_render(n_objects=4, per_object=8, seed=args.seed))
    results.update(bench_feasibility(episodes=80, seed=args.seed))
    results["meta"] = {
        "command": " ".join([Path(sys.executable).name, *sys.argv]),
        "mujoco": mujoco.__version__,
        "numpy": np.__version__,
        "python": platform.python_version(),
        "platform": platform.platform(),
        "cpu_count": os.cpu_count(),
        "cpu": platform.processor() or platform.machine(),
        "mujoco_gl": os.environ.get("MUJOCO_GL"),
        "seconds": args.seconds,
        "goals": args.goals,
        "contacts": args.contacts,
        "seed": args.seed,
        "wall_s": round(time.perf_counter() - t0, 1),
        "time": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    print_table(results)
    if args.json is not None:
        write_json_atomic(args.json, results)
        print(f"wrote {args.json}")
    return results


if __name__ == "__main__":
    main()
