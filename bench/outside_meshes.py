"""A policy on meshes outside the object set: generated OBJ files against the unseen split.

hydo's object set (sim/objects.py) is procedural: boxes, cylinders, cones, mugs, tori and the
like, each category with train and unseen instances. A user brings other shapes. This bench writes
a fixed set of such meshes (trimesh, seeded, so every run makes the same files) and evaluates one
policy on them and on ``--objects unseen`` with the same episode seed, as
``hydo eval MODEL --goals G --objects DIR`` and ``--objects unseen`` would:

- ``blob``: convex hulls of 40 points on a random ellipsoid (3–6 cm radii);
- ``rock``: an icosphere with radial noise, stretched (slightly concave; collides as its hull);
- ``multi``: two or three boxes, spheres and cylinders joined off-centre (an irregular multi-part
  body; collides as its pieces);
- ``household``: scaled-down everyday shapes: a hex nut, a square pyramid, an L-bracket, a
  dumbbell, a bottle, a triangular wedge.

User meshes collide as one convex part per separate piece of the file (``sim.objects.load_user_mesh``;
before session 42 as one hull of the whole), so the multi-part bodies, the L-bracket, the dumbbell
and the bottle push like what they are; a concave single piece (the rocks) pushes like its hull
but is observed (and its goal flow computed) on its true surface.

Usage::

    python bench/outside_meshes.py --model models/hydo-cm-6d --goals 6d --episodes 500 --seed 1 \\
        --mesh-dir runs/outside-meshes --json runs/bench-outside.json

JSON: ``{"outside": {...}, "unseen": {...}, "gap": unseen − outside, "meta": {...}}``, each set with
``success_rate``, ``move`` / ``flip`` and ``per_object`` ``{name: [successes, episodes]}``.
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
import trimesh  # noqa: E402

from hydo_cli.envs import make_envs  # noqa: E402
from hydo_cli.policies import load_policy  # noqa: E402
from hydo_cli.report import goal_kind_breakdown  # noqa: E402
from hydo_cli.rollout import run_episodes, summarize  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402
from sim.contract import CONTACT_DEFAULT, CONTACT_MODELS  # noqa: E402

N_ENVS = 8  # envs stepped in lock-step, one batched decision per step (as hydo eval)


def _blob(rng: np.random.Generator) -> trimesh.Trimesh:
    d = rng.normal(size=(40, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return trimesh.convex.convex_hull(d * rng.uniform(0.03, 0.06, 3))


def _rock(rng: np.random.Generator) -> trimesh.Trimesh:
    m = trimesh.creation.icosphere(subdivisions=2, radius=1.0)
    r = 1.0 + 0.15 * rng.uniform(-1, 1, len(m.vertices))
    return trimesh.Trimesh(m.vertices * r[:, None] * rng.uniform(0.025, 0.055, 3), m.faces)


def _part(rng: np.random.Generator) -> trimesh.Trimesh:
    kind = rng.integers(3)
    if kind == 0:
        return trimesh.creation.box(extents=rng.uniform(0.02, 0.07, 3))
    if kind == 1:
        return trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.015, 0.035))
    return trimesh.creation.cylinder(radius=rng.uniform(0.012, 0.03), height=rng.uniform(0.03, 0.08))


def _multi(rng: np.random.Generator) -> trimesh.Trimesh:
    parts = []
    for k in range(int(rng.integers(2, 4))):
        p = _part(rng)
        R = trimesh.transformations.random_rotation_matrix(rng.random(3))
        R[:3, 3] = 0.0 if k == 0 else rng.uniform(-0.03, 0.03, 3)
        parts.append(p.apply_transform(R))
    return trimesh.util.concatenate(parts)


def _household() -> list[tuple[str, trimesh.Trimesh]]:
    cyl = trimesh.creation.cylinder
    box = trimesh.creation.box

    def at(m: trimesh.Trimesh, xyz) -> trimesh.Trimesh:
        return m.apply_translation(xyz)

    bell = [at(trimesh.creation.icosphere(2, 0.025), (0, 0, z)) for z in (-0.05, 0.05)]
    return [
        ("hex_nut", cyl(radius=0.035, height=0.025, sections=6)),
        ("pyramid", trimesh.creation.cone(radius=0.05, height=0.06, sections=4)),
        ("l_bracket", trimesh.util.concatenate([box((0.09, 0.03, 0.02)), at(box((0.02, 0.03, 0.06)), (0.035, 0, 0.04))])),
        ("dumbbell", trimesh.util.concatenate([*bell, cyl(radius=0.01, height=0.08)])),
        ("bottle", trimesh.util.concatenate([cyl(radius=0.03, height=0.1), at(cyl(radius=0.012, height=0.04), (0, 0, 0.07))])),
        ("wedge", trimesh.convex.convex_hull([(x, y, z) for x, z in ((0, 0), (0.08, 0), (0, 0.04)) for y in (0, 0.05)])),
    ]  # fmt: skip


def write_meshes(folder: Path, per_kind: int = 6, seed: int = 0) -> list[Path]:
    """Write the outside set (``3 · per_kind`` generated meshes plus the household shapes) as OBJ
    files in metres to ``folder``; the same ``seed`` gives the same files."""
    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    meshes = [(f"{name}_{i:02d}", make(rng)) for name, make in (("blob", _blob), ("rock", _rock), ("multi", _multi))
              for i in range(per_kind)] + _household()  # fmt: skip
    paths = []
    for name, m in meshes:
        path = folder / f"{name}.obj"
        atomic_write_text(
            path, trimesh.exchange.obj.export_obj(m, include_normals=False, include_texture=False)
        )
        paths.append(path)
    return paths


def evaluate(model: str, objects: str, goals: str, episodes: int, seed: int, contacts: str | None) -> dict:
    """One policy on one object set; ``contacts`` None plays in the model's own (as ``hydo eval``)."""
    lp = load_policy(model, seed=seed)
    contacts = contacts or lp.contacts or CONTACT_DEFAULT
    envs = make_envs(objects, goals, 0, "mesh", N_ENVS, lp.n_obj, lp.n_bg, contacts=contacts)
    t0 = time.perf_counter()
    eps = run_episodes(envs, lp.policy, episodes, seed=seed)
    for env in envs:
        env.close()
    per_object: dict = {}
    for e in eps:
        o = per_object.setdefault(e.object, [0, 0])
        o[0] += int(e.success)
        o[1] += 1
    return {
        **summarize(eps),
        **goal_kind_breakdown(eps),
        "per_object": per_object,
        "contacts": contacts,
        "wall_s": time.perf_counter() - t0,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", required=True, help="exported model folder or training run (as hydo eval)")
    ap.add_argument("--goals", choices=("planar", "6d"), default="6d")
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--contacts", choices=CONTACT_MODELS, help="the scene's contact model (default: the model's own)"
    )
    ap.add_argument("--per-kind", type=int, default=6, help="generated meshes per kind (blob, rock, multi)")
    ap.add_argument("--mesh-dir", type=Path, default=Path("runs/outside-meshes"))
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()

    paths = write_meshes(args.mesh_dir, args.per_kind)
    print(f"{len(paths)} meshes in {args.mesh_dir}", flush=True)
    results = {}
    for name, objects in (("outside", str(args.mesh_dir)), ("unseen", "unseen")):
        r = results[name] = evaluate(args.model, objects, args.goals, args.episodes, args.seed, args.contacts)
        mf = "  ".join(
            f"{k} {r[k]['success_rate']:.1%} of {r[k]['episodes']}" for k in ("move", "flip") if k in r
        )
        print(f"{name:<8} success {r['success_rate']:.1%}   {mf}   ({r['wall_s']:.0f} s)", flush=True)
    results["gap"] = results["unseen"]["success_rate"] - results["outside"]["success_rate"]
    print(f"gap (unseen − outside): {100 * results['gap']:+.1f} points")
    worst = sorted(results["outside"]["per_object"].items(), key=lambda kv: kv[1][0] / kv[1][1])[:6]
    print("weakest outside meshes: " + ", ".join(f"{k} {s}/{n}" for k, (s, n) in worst))
    if args.json:
        meta = {
            "command": " ".join(sys.argv),
            "python": platform.python_version(),
            "meshes": [p.name for p in paths],
        }
        atomic_write_text(args.json, json.dumps({**results, "meta": meta}, indent=2))


if __name__ == "__main__":
    main()
