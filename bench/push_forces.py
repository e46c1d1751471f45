"""How hard the training hand pushes: the peak force of each primitive against the arm's force stop.

The training env's hand (``sim/assets/hand.xml``) is a force-limited position servo: up to 40 N on
each horizontal axis and 60 N vertically, and it ends a primitive when its net contact force passes
``sim.primitive.FORCE_STOP_N`` (30 N; ``--no-stop``: it pushes on, as before that stop existed). A
Franka in the cell stops a push when its external force passes ``limits.force_stop_n`` (30 N in the
example cell) and trips its reflex at 40 N. A policy
that learned to flip by pressing harder than that meets force stops on the arm that it never met
in training. This bench runs a policy in the training env (``hydo eval --seed``'s episodes) and
records, per primitive, the peak norm of the net contact force on the hand (what the arm's
external-force estimate measures, as ``robot.twin`` computes it), split by move / flip goals and by
whether the episode succeeded.

Usage::

    python bench/push_forces.py --model models/hydo-cm-6d --goals 6d --episodes 100 --seed 5 \\
        --json runs/bench-push-forces.json

JSON: ``{"move": {...}, "flip": {...}, "meta": {...}}``; each with the primitives, the fraction whose
peak passes the force stop and the reflex, and peak quantiles (N).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from hydo_cli.envs import make_envs  # noqa: E402
from hydo_cli.policies import load_policy  # noqa: E402
from hydo_cli.rollout import run_episodes  # noqa: E402
from robot.cell import load_cell  # noqa: E402
from sim import scene as scene_module  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402
from sim.goals import FLIP_TILT_DEG  # noqa: E402
from sim.primitive import FORCE_STOP_N  # noqa: E402


def hand_force_recorder(peaks: list[float], stops: list[bool], stop: bool = True):
    """Wrap ``BinScene._run_controls`` so that each call appends its peak hand force (N) to ``peaks``
    (up to the step the contact-force stop ended it) and whether the stop did to ``stops``.
    ``stop=False``: the hand pushes on to its actuator limits (the training hand before the stop)."""
    original = scene_module.BinScene._run_controls

    def run_controls(self, controls, force_stop_n=None):
        force_stop_n = force_stop_n if stop else None
        m, d = self.model, self.data
        # the rollout keeps no contacts: step the same controls in a copy (warm start included, so
        # the same trajectory) and read the net contact force on the hand after each step
        d2 = mujoco.MjData(m)
        mujoco.mj_copyData(d2, m, d)
        f6 = np.zeros(6)
        forces = np.zeros(len(controls))
        for t, c in enumerate(controls):
            d2.ctrl[:] = c
            mujoco.mj_step(m, d2)
            if d2.ncon == 0:
                continue
            geoms = d2.contact.geom[: d2.ncon]
            on1, on2 = self._is_hand_geom[geoms[:, 0]], self._is_hand_geom[geoms[:, 1]]
            total = np.zeros(3)
            for i in np.flatnonzero(on1 ^ on2):
                mujoco.mj_contactForce(m, d2, int(i), f6)
                f = d2.contact.frame[i].reshape(3, 3).T @ f6[:3]
                total += f if on2[i] else -f
            forces[t] = float(np.linalg.norm(total))
        stopped_at = original(self, controls, force_stop_n)
        peaks.append(float(forces[: None if stopped_at is None else stopped_at + 1].max(initial=0.0)))
        stops.append(stopped_at is not None)
        return stopped_at

    scene_module.BinScene._run_controls = run_controls


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True)
    ap.add_argument("--goals", choices=("planar", "6d"), default="6d")
    ap.add_argument("--objects", default="train")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--cell", type=Path, default=None, help="cell YAML whose force limits to compare with")
    ap.add_argument(
        "--no-stop",
        action="store_true",
        help="the hand pushes on past sim.primitive.FORCE_STOP_N (the training env before the stop)",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    limits = load_cell(args.cell, reach=False).limits
    lp = load_policy(args.model, seed=args.seed)
    (env,) = make_envs(args.objects, args.goals, 0, "mesh", 1, lp.n_obj, lp.n_bg)
    peaks: list[float] = []
    stops: list[bool] = []
    hand_force_recorder(peaks, stops, stop=not args.no_stop)
    t0 = time.perf_counter()
    results = []  # (episode result, its primitives' peaks); one env, so episodes run one at a time
    mark = [0]

    def on_episode(r) -> None:
        results.append((r, peaks[mark[0] :], stops[mark[0] :]))
        mark[0] = len(peaks)

    run_episodes([env], lp.policy, args.episodes, seed=args.seed, on_episode=on_episode)
    wall = time.perf_counter() - t0
    out: dict = {}
    for kind in ("move", "flip"):
        rows = [(r, p) for r, p, _ in results if (r.goal_tilt_deg >= FLIP_TILT_DEG) == (kind == "flip")]
        if not rows:
            continue
        stopped = [
            x for r, _, st in results if (r.goal_tilt_deg >= FLIP_TILT_DEG) == (kind == "flip") for x in st
        ]
        allp = np.array([x for _, p in rows for x in p])
        won = np.array([x for r, p in rows if r.success for x in p])
        out[kind] = {
            "episodes": len(rows),
            "success_rate": float(np.mean([r.success for r, _ in rows])),
            "primitives": int(len(allp)),
            "over_force_stop": float((allp > limits.force_stop).mean()),
            "over_reflex": float((allp > limits.collision_force).mean()),
            "over_force_stop_in_successes": float((won > limits.force_stop).mean()) if len(won) else None,
            "episodes_with_a_push_over_force_stop": float(
                np.mean([max(p, default=0) > limits.force_stop for _, p in rows])
            ),
            "force_stopped": float(np.mean(stopped)),  # primitives the training hand's stop ended
            "peak_n_median": float(np.median(allp)),
            "peak_n_p90": float(np.quantile(allp, 0.9)),
        }
        s = out[kind]
        print(
            f"{kind}: {s['episodes']} episodes ({s['success_rate']:.0%} success), {s['primitives']} primitives; "
            f"peak force median {s['peak_n_median']:.0f} N, p90 {s['peak_n_p90']:.0f} N; over the {limits.force_stop:.0f} N "
            f"stop {s['over_force_stop']:.1%} (in successful episodes {s['over_force_stop_in_successes'] or 0:.1%}), "
            f"over the {limits.collision_force:.0f} N reflex {s['over_reflex']:.1%}; episodes with such a push "
            f"{s['episodes_with_a_push_over_force_stop']:.0%}; stopped by the training hand's "
            f"{FORCE_STOP_N:.0f} N stop {s['force_stopped']:.1%}"
        )
    print(f"wall {wall:.0f} s")
    if args.json:
        meta = {"command": " ".join(sys.argv), "python": platform.python_version(), "wall_s": wall}
        atomic_write_text(args.json, json.dumps({**out, "meta": meta}, indent=2))


if __name__ == "__main__":
    main()
