"""Where a policy loses success on rendered depth: which points it sees, or the normals it is given.

``hydo eval --obs render`` gives the policy the deploy path's clouds (three rendered depth cameras,
background subtraction, PCA normals); training gives it mesh-surface samples with their exact
normals, those the cameras see. Two things differ, and this bench swaps one at a time on the same
episodes (``hydo eval --seed``'s):

- ``mesh-all``: mesh samples on every side not facing or touching the floor, the training
  observation before it kept only what the cameras see (``MeshObserver(cameras=False)``);
- ``mesh``: the training observation (the samples the cameras see, by a z-buffer);
- ``mesh-seen``: mesh samples, only those within ``SEEN_M`` of a rendered point (the surface the
  cameras see), exact normals: the rendered *coverage* with the training's geometry;
- ``mesh-pca``: the training observation's samples with PCA normals (``sim.depth.estimate_normals``,
  the deploy path's estimator, turned to the outward side): the deploy *normal estimator* alone;
- ``render-mesh-normals``: the rendered points, each with the exact normal of the nearest mesh
  sample: the rendered points with the training's *normals*;
- ``render``: the deploy path's observation;
- ``mesh-render-bg``: the training observation's object samples with the rendered *background*
  (back-projected bin pixels) instead of the training's fixed grid on the bin's surfaces;
- ``render-grid-bg``: the deploy path's object points and normals with the training's background grid;
- ``mesh-pose-noise``: the training observation seen from a pose off the true one, as model
  registration's fit is (``--pose-noise-mm`` / ``--pose-noise-deg``, normal per axis): the object's
  samples moved by the error and the goal flow from that pose to a goal pose off the same way (drawn
  once per goal); reward and success stay the truth's. What the fitted pose alone costs the policy.

``mesh`` → ``mesh-seen`` is what the rest of the rendered coverage costs; ``render-mesh-normals`` → ``render`` is what PCA
normals cost. Per variant: success, per move / flip and per object.

Usage::

    python bench/render_gap.py --model models/hydo-cm-6d --goals 6d --episodes 100 --seed 5 \\
        --variants mesh-all,mesh,mesh-seen,render-mesh-normals,render --json runs/bench-render-gap.json

JSON: ``{variant: {"success_rate", "move", "flip", "per_object", "wall_s"}, "meta": {...}}``.
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

import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

from hydo_cli.envs import make_envs  # noqa: E402
from hydo_cli.policies import load_policy  # noqa: E402
from hydo_cli.report import goal_kind_breakdown  # noqa: E402
from hydo_cli.rollout import run_episodes, summarize  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402
from sim.contract import SymmetricGoals, build_observation, transform_points  # noqa: E402
from sim.depth import NORMAL_K, estimate_normals  # noqa: E402
from sim.observe import MeshObserver  # noqa: E402

VARIANTS = (
    "mesh-all",
    "mesh",
    "mesh-seen",
    "mesh-pca",
    "render-mesh-normals",
    "render",
    "mesh-render-bg",
    "render-grid-bg",
    "mesh-pose-noise",
)
SEEN_M = 0.005  # a mesh sample this close to a rendered point is on the surface the cameras see


class HybridObserver:
    """``segmented_clouds`` of a variant that mixes the rendered and the mesh clouds (see above)."""

    def __init__(self, variant: str, render):
        self.variant, self.render, self.mesh = variant, render, MeshObserver()
        self.name = variant

    def segmented_clouds(self, scene):
        r_p, r_n, r_bg = self.render.segmented_clouds(scene)
        m_p, m_n, m_bg = self.mesh.segmented_clouds(scene)
        if self.variant == "mesh-render-bg":
            return m_p, m_n, r_bg
        if self.variant == "render-grid-bg":
            return r_p, r_n, m_bg
        if self.variant == "mesh-pca":
            n = estimate_normals(m_p, NORMAL_K)
            n[(n * m_n).sum(axis=1) < 0] *= -1  # deploy turns them towards the camera: the outward side
            return m_p, n, m_bg
        if self.variant == "mesh-seen":
            d, _ = cKDTree(r_p).query(m_p)
            keep = d < SEEN_M
            if keep.sum() < 8:  # nothing rendered near the samples: as the render observer's fallback
                return m_p, m_n, m_bg
            return m_p[keep], m_n[keep], m_bg
        # render-mesh-normals: each rendered point with the exact normal of the nearest mesh sample
        _, j = cKDTree(m_p).query(r_p)
        return r_p, m_n[j], r_bg

    def close(self):
        self.render.close()


def _pose_error(rng, sigma_m: float, sigma_deg: float) -> np.ndarray:
    """A (4, 4) object-frame pose error: rotation vector and translation, normal per axis."""
    E = np.eye(4)
    E[:3, :3] = Rotation.from_rotvec(rng.normal(size=3) * np.deg2rad(sigma_deg)).as_matrix()
    E[:3, 3] = rng.normal(size=3) * sigma_m
    return E


def observe_from_a_pose_off(env, rng, sigma_m: float, sigma_deg: float) -> None:
    """``mesh-pose-noise``: ``env``'s observation as from a fitted pose (see the module docstring)."""
    goal_error: dict = {}

    def _observe() -> dict:
        env._refresh_goal()  # the true goal and the symmetries, for reward and success
        obj_p, obj_n, bg = env.observer.segmented_clouds(env.scene)
        T = env.scene.object_T()
        T_fit = T @ _pose_error(rng, sigma_m, sigma_deg)
        moved = T_fit @ np.linalg.inv(T)  # world frame: true pose -> fitted pose
        key = env.T_goal.tobytes()
        if key not in goal_error:  # a new goal: its pose off once, its symmetric poses ready (as the env)
            asset = env.scene.asset
            T_goal_off = env.T_goal @ _pose_error(rng, sigma_m, sigma_deg)
            goal_error.clear()
            goal_error[key] = SymmetricGoals(T_goal_off, asset.surface_points, env._symmetries[asset.name])
        goals = goal_error[key]
        obs = build_observation(
            transform_points(moved, obj_p).astype(np.float32),
            (obj_n @ moved[:3, :3].T).astype(np.float32),
            bg,
            T_fit,
            goals.nearest(T_fit),
            env.n_obj,
            env.n_bg,
            env.np_random,
        )
        env._obs = obs
        return obs

    env._observe = _observe


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="exported model folder or training run (as hydo eval)")
    ap.add_argument("--goals", choices=("planar", "6d"), default="6d")
    ap.add_argument("--objects", default="train")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--variants", default=",".join(VARIANTS))
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--policy-seed",
        type=int,
        help="the policy's sampling seed (default: --seed, as hydo eval): the same episodes, other draws",
    )
    ap.add_argument(
        "--pose-noise-mm", type=float, default=2.0, help="mesh-pose-noise: translation σ per axis"
    )
    ap.add_argument("--pose-noise-deg", type=float, default=2.0, help="mesh-pose-noise: rotation σ per axis")
    args = ap.parse_args()
    variants = [v.strip() for v in args.variants.split(",") if v.strip()]
    if bad := [v for v in variants if v not in VARIANTS]:
        ap.error(f"unknown variants {bad}; choose from {list(VARIANTS)}")

    results: dict = {}
    lp = load_policy(args.model, seed=args.seed if args.policy_seed is None else args.policy_seed)
    for v in variants:
        (env,) = make_envs(
            args.objects,
            args.goals,
            0,
            "mesh" if v in ("mesh", "mesh-all", "mesh-pose-noise") else "render",
            1,
            lp.n_obj,
            lp.n_bg,
        )
        if v == "mesh-all":
            env.observer = MeshObserver(cameras=False)
        elif v == "mesh-pose-noise":
            rng = np.random.default_rng(args.seed)
            observe_from_a_pose_off(env, rng, args.pose_noise_mm / 1000, args.pose_noise_deg)
        elif v not in ("mesh", "render"):
            env.observer = HybridObserver(v, env.observer)
        t0 = time.perf_counter()
        eps = run_episodes([env], lp.policy, args.episodes, seed=args.seed)
        env.close()
        per_object: dict = {}
        for e in eps:
            o = per_object.setdefault(e.object, [0, 0])
            o[0] += e.success
            o[1] += 1
        results[v] = {
            **summarize(eps),
            **goal_kind_breakdown(eps),
            "per_object": per_object,
            "wall_s": time.perf_counter() - t0,
            "successes": [bool(e.success) for e in eps],
        }
        r = results[v]
        mf = "  ".join(
            f"{k} {r[k]['success_rate']:.0%} of {r[k]['episodes']}" for k in ("move", "flip") if k in r
        )
        print(f"{v:<22} success {r['success_rate']:.0%}   {mf}   ({r['wall_s']:.0f} s)", flush=True)
    if args.json:
        meta = {"command": " ".join(sys.argv), "python": platform.python_version()}
        atomic_write_text(args.json, json.dumps({**results, "meta": meta}, indent=2))


if __name__ == "__main__":
    main()
