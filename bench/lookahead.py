"""Headroom of the task: the success a one-step lookahead search over pushes reaches.

At every step the searcher tries ``C`` candidate pushes in the simulator itself (four from the
``heuristic`` policy, the rest a uniformly random object point and motion), goes back to the saved
state after each (``BinEnv.get_sim_state`` / ``set_sim_state``, MuJoCo's full integration state, so a
replayed push ends exactly where it did when tried), then executes the one that ended closest to the
goal. It sees the simulator, so it is not a policy a robot could run; it tells how much of the gap
between a learned policy and 100 % the push primitive and the physics leave open. A learned policy
near the searcher's figure is limited by the task; far below it, by the learner.

With ``--run RUN`` the candidates are a trained policy's own: its proposed motion at each of the
``--top`` object points it ranks highest (masked Q, as ``hydo eval`` decides). ``top = 1`` is the
policy itself; the success at larger ``top`` is what a better *ranking* of the same proposals would
reach, so the gap separates a critic that ranks poorly from motions that are poor.

Usage::

    python bench/lookahead.py --candidates 8,48 --episodes 40 --json runs/bench-lookahead.json
    python bench/lookahead.py --run runs/train/hydo-cm-s1 --top 1,4,16 --episodes 40

JSON: ``{"C=<n>": {"success_rate", "mean_steps_to_success", "mean_final_distance_m",
"max_replay_error_m", "wall_s", "episodes", "move_success_rate", "flip_success_rate", ...}, "meta":
{...}}``; ``max_replay_error_m`` is the largest difference between a push's distance when tried and
when executed (0 when replay is exact); ``flip`` episodes are those whose goal puts another face up
(``hydo_cli.report.FLIP_TILT_DEG``), ``move`` the rest.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ["OPENBLAS_NUM_THREADS"] = "1"
os.environ["OMP_NUM_THREADS"] = "1"
ROOT = Path(__file__).resolve().parent.parent
sys.path[:] = [str(ROOT)] + [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from sim.atomic import atomic_write_text  # noqa: E402
from sim.baselines import heuristic_action  # noqa: E402
from sim.contract import CONTACT_DEFAULT, CONTACT_MODELS  # noqa: E402
from sim.env import BinEnv  # noqa: E402
from sim.goals import FLIP_TILT_DEG  # noqa: E402

N_HEURISTIC = 4  # heuristic candidates per step (it samples among its contact points)


def random_candidates(n_candidates: int, rng: np.random.Generator):
    """``N_HEURISTIC`` heuristic pushes, the rest uniform over object points and motions."""

    def propose(obs):
        n_obj = len(obs["normals"])
        candidates = [heuristic_action(obs, rng) for _ in range(N_HEURISTIC)]
        return candidates + [
            (int(rng.integers(n_obj)), rng.uniform(-1.0, 1.0, 3)) for _ in range(n_candidates - N_HEURISTIC)
        ]

    return propose


def policy_candidates(agent, top: int, seed: int):
    """A trained agent's proposals at its ``top`` highest-ranked feasible points, best first (the
    ranking ``hydo eval`` decides on: ``HybridAgent.act``'s masked Q)."""
    import torch

    from hydo_cli.policies import stack_obs
    from sim.primitive import feasibility_mask

    generator = torch.Generator().manual_seed(seed)

    def propose(obs):
        points, features = stack_obs([obs])
        normals = obs["normals"][None]
        feasible = feasibility_mask(points.numpy(), normals)
        with torch.no_grad():
            _, _, info = agent.act(
                points,
                features,
                mode="eval",
                generator=generator,
                normals=torch.from_numpy(normals),
                feasible=feasible,
            )
        motions = info["motions"][0].numpy()  # (N_obj, 3)
        order = np.argsort(-info["q_select"][0].numpy(), kind="stable")[:top]
        return [(int(i), motions[i]) for i in order]

    return propose


def try_push(env, snapshot, action) -> float:
    """Distance after ``action`` tried from ``snapshot`` (inf if refused or the object left the bin),
    then back to the snapshot."""
    _, _, _, _, tried = env.step(action)
    env.set_sim_state(snapshot)
    bad = tried["rejected"] or tried["failure"] == "object_left_bin"
    return np.inf if bad else tried["distance"]


def search_episode(env, propose, seed: int) -> dict:
    """One episode of greedy one-step search over ``propose(obs)``'s candidates; returns its outcome
    and the largest replay error."""
    obs, info = env.reset(seed=seed)
    tilt = info["goal_tilt_deg"]
    replay_error, steps = 0.0, 0
    while True:
        snapshot = env.get_sim_state()
        best, best_d = None, np.inf
        for action in propose(obs):
            d = try_push(env, snapshot, action)
            if best is None or d < best_d:
                best, best_d = action, d
        obs, _, terminated, truncated, info = env.step(best)
        steps += 1
        if np.isfinite(best_d):
            replay_error = max(replay_error, abs(info["distance"] - best_d))
        if terminated or truncated:
            return {
                "object": info["object"],
                "success": bool(info["success"]),
                "steps": steps,
                "final_distance": float(info["distance"]),
                "replay_error": replay_error,
                "flip": tilt >= FLIP_TILT_DEG,
            }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--candidates", default="8,48", help="comma-separated candidate counts C (≥ 4)")
    ap.add_argument("--run", type=Path, help="search over this run's (or checkpoint's) own proposals")
    ap.add_argument(
        "--top", default="1,4,16", help="with --run: comma-separated numbers of top-ranked points"
    )
    ap.add_argument("--episodes", type=int, default=40)
    ap.add_argument("--objects", default="train")
    ap.add_argument("--goals", default="planar", choices=["planar", "6d"])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--contacts",
        choices=CONTACT_MODELS,
        help="the scene's contact model (default: the run's own with --run, else hydo's)",
    )
    ap.add_argument("--json", type=Path, help="write results to this JSON file")
    args = ap.parse_args()
    if args.run is None:
        counts = [int(c) for c in args.candidates.split(",")]
        if min(counts) < N_HEURISTIC:
            ap.error(f"--candidates must each be ≥ {N_HEURISTIC}")
        n_obj, n_bg = 128, 128
        args.contacts = args.contacts or CONTACT_DEFAULT
    else:
        import torch

        from hydo_cli.policies import load_agent

        torch.set_num_threads(1)
        agent, cfg, _ = load_agent(args.run)
        counts = [int(c) for c in args.top.split(",")]
        n_obj, n_bg = cfg.n_obj, cfg.n_bg
        args.contacts = args.contacts or cfg.contacts

    env = BinEnv(objects=args.objects, goals=args.goals, n_obj=n_obj, n_bg=n_bg, contacts=args.contacts)
    results = {}
    for c in counts:
        rng = np.random.default_rng(args.seed)
        propose = random_candidates(c, rng) if args.run is None else policy_candidates(agent, c, args.seed)
        t0 = time.perf_counter()
        eps = [search_episode(env, propose, args.seed * 100_000 + i) for i in range(args.episodes)]
        ok = [e for e in eps if e["success"]]
        kinds = {k: [e["success"] for e in eps if e["flip"] == (k == "flip")] for k in ("move", "flip")}
        results[f"{'top' if args.run else 'C'}={c}"] = {
            "candidates": c,
            "episodes": len(eps),
            "success_rate": len(ok) / len(eps),
            "mean_steps_to_success": float(np.mean([e["steps"] for e in ok])) if ok else None,
            "mean_final_distance_m": float(np.mean([e["final_distance"] for e in eps])),
            "max_replay_error_m": float(max(e["replay_error"] for e in eps)),
            # 6D goals: success where the goal keeps the face up, and where it asks for a flip
            **{f"{k}_episodes": len(v) for k, v in kinds.items()},
            **{f"{k}_success_rate": float(np.mean(v)) if v else None for k, v in kinds.items()},
            "wall_s": time.perf_counter() - t0,
        }

    source = f"{args.run}'s top-ranked proposals" if args.run else "heuristic + random candidates"
    table = Table(
        title=f"one-step lookahead over {source} ({args.objects} objects, {args.goals} goals, {args.contacts} contacts)"
    )
    for col in (
        "top" if args.run else "candidates",
        "episodes",
        "success",
        "move / flip",
        "steps to success",
        "final dist (cm)",
        "replay err (mm)",
        "wall s",
    ):
        table.add_column(col, justify="right")
    for r in results.values():
        steps = "-" if r["mean_steps_to_success"] is None else f"{r['mean_steps_to_success']:.1f}"
        table.add_row(
            str(r["candidates"]),
            str(r["episodes"]),
            f"{r['success_rate']:.0%}",
            " / ".join(
                "-" if r[f"{k}_success_rate"] is None else f"{r[f'{k}_success_rate']:.0%}"
                for k in ("move", "flip")
            ),
            steps,
            f"{r['mean_final_distance_m'] * 100:.1f}",
            f"{r['max_replay_error_m'] * 1000:.2f}",
            f"{r['wall_s']:.0f}",
        )
    Console().print(table)
    if args.json:
        meta = {"command": "python " + " ".join(sys.argv), "python": platform.python_version(), **vars(args)}
        meta["json"] = str(args.json)
        atomic_write_text(args.json, json.dumps({**results, "meta": meta}, indent=2, default=str))


if __name__ == "__main__":
    main()
