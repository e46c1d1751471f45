"""Registration on the twin's cameras: how often it refuses, and how far off it is, per goal kind.

Deploy estimates the goal flow by registering the current object cloud to the goal cloud
(``robot.registration``). This bench measures that step alone, with the twin's truth and without a
policy or an arm: per episode (``hydo eval --seed``'s episodes: same object, start and goal), the
object is placed at its goal pose, captured through the cell's cameras and segmented (the goal
cloud, as ``hydo deploy capture-goal`` records it), then captured at two more poses:

- ``start``: the episode's start pose. On 6D goals about half need a flip, so the two views often
  show different faces: the case that makes view-to-view registration hard;
- ``near``: the goal pose moved by 1–4 cm and turned up to 20° about the vertical: where the loop
  decides success, so the registration's distance must agree with the true one about 3 cm;
- ``turned``: the goal pose moved by up to 1 cm and turned 60–180° about the vertical: the body in
  place, a mug's handle or a box's long side elsewhere. Up to the object's symmetry that is the goal
  (a cylinder, a bowl) or 3 cm and more from it (a mug): the case behind the twin's false successes.

For each: refused or not (the cell's ``registration_max_rmse`` / ``registration_min_inliers`` /
``registration_min_overlap``), the inlier fraction and the overlap the registration implies, ADD-S
of the estimated transform against the true one, its ADD (``flow_add``: the goal flow's error point
for point, which ADD-S does not see on symmetric and nearly symmetric objects), and (``near``)
whether the 3 cm verdict agrees with the truth. The deploy loop's verdict (``Registration.verdict`` with the cell's success margin) is counted
against the truth: ``false_success`` (it says success, the truth is 3 cm or more), ``false_failure``,
``undecided`` (ambiguous or uncertain). Printed as a table, per ``move`` / ``flip`` (goal tilt ≥ 30°)
and per object.

Usage::

    python bench/registration.py --goals 6d --episodes 100 --seed 5 --json runs/bench-registration.json

JSON: ``{"start": {...}, "near": {...}, "per_object": {...}, "episodes": [...], "meta": {...}}``; with
``--registration model`` also ``"goal_fit"``: the goal's model fit against the true goal pose (ADD up
to the object's symmetry; median, and how many are over 5 mm).
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

from robot import registration  # noqa: E402
from robot.cell import load_cell  # noqa: E402
from robot.connect import open_cameras  # noqa: E402
from robot.errors import RegistrationError  # noqa: E402
from robot.model_registration import ModelRegistration, ObjectModel  # noqa: E402
from robot.perception import capture_background, segment  # noqa: E402
from robot.registration import INLIER_M, check_registration, goal_visible, register_checked  # noqa: E402
from robot.twin import TwinWorld, sample_episode  # noqa: E402
from robot.twin_metrics import (  # noqa: E402
    nearest_true_goal,
    registration_add,
    registration_error,
    true_distance,
)
from sim.atomic import atomic_write_text  # noqa: E402
from sim.contract import transform_points  # noqa: E402
from sim.goals import FLIP_TILT_DEG, episode_seed, tilt_deg  # noqa: E402
from sim.objects import load_objects  # noqa: E402
from sim.symmetry import symmetries  # noqa: E402

SUCCESS_M = 0.03
NEAR_SHIFT_M = (0.01, 0.04)
NEAR_YAW_DEG = 20.0
TURNED_SHIFT_M = 0.01
TURNED_YAW_DEG = (60.0, 180.0)
CASES = ("start", "near", "turned")


def _quat_yaw(quat_wxyz: np.ndarray, yaw: float) -> np.ndarray:
    """``quat_wxyz`` turned by ``yaw`` rad about the world vertical."""
    w, x, y, z = quat_wxyz
    c, s = np.cos(yaw / 2), np.sin(yaw / 2)  # q_yaw = (c, 0, 0, s); q_yaw * q
    return np.array([c * w - s * z, c * x - s * y, c * y + s * x, c * z + s * w])


def _goal_fit_add(model_reg, T_goal: np.ndarray, bin_center: np.ndarray) -> float:
    """ADD (m) of the goal's model fit against the true goal pose (base frame), up to the object's
    symmetry: where the fit puts the model's surface samples against where the goal pose does."""
    T_fit = model_reg.goal.T.copy()
    T_fit[:3, 3] += bin_center  # bin frame -> base frame
    pts = model_reg.model.points
    fitted = transform_points(T_fit, pts)
    return min(
        float(np.linalg.norm(fitted - transform_points(T_goal @ S, pts), axis=1).mean())
        for S in model_reg.model.symmetries
    )


def measure(cell, world, cams, background, T_goal, goal_points, mode, seed, rng, model_reg=None) -> dict:
    """Register the object's current cloud to ``goal_points``; the residuals and errors vs the truth.
    ``model_reg``: the episode's ``robot.model_registration.ModelRegistration`` (``--registration
    model``), else view-to-view registration."""
    seg = segment(cams.capture(), background, cell, rng)
    if model_reg is not None:
        model_reg.last = None  # each case on its own, as a first step: no pose from before
        reg, widened = model_reg.register(seg.obj_points, seed), False
    else:
        reg, widened = register_checked(
            seg.obj_points, goal_points, mode, seed, cell.cameras, cell.perception
        )
    p = cell.perception
    try:
        check_registration(
            reg, p.registration_max_rmse, p.registration_min_inliers, p.registration_min_overlap
        )
        refused = None
    except RegistrationError as e:
        refused = str(e)
    true_d = true_distance(world, T_goal)
    # the earlier test (before registration.goal_visible): inliers over all current points
    d, _ = cKDTree(goal_points).query(transform_points(reg.T, seg.obj_points))
    inliers_all = float((d < INLIER_M).mean())
    # the same test with the true transform: what the clouds allow, whatever the fit
    moved = transform_points(
        nearest_true_goal(world, T_goal) @ np.linalg.inv(world.object_T()), seg.obj_points
    )
    d, _ = cKDTree(goal_points).query(moved)
    seen = goal_visible(moved, goal_points, cell.cameras)
    inliers_true = float((d[seen] < INLIER_M).mean())
    inliers_true_all = float((d < INLIER_M).mean())
    return {
        "refused": refused,
        "widened": widened,
        "refused_all_points_rule": bool(
            reg.rmse > p.registration_max_rmse or inliers_all < p.registration_min_inliers
        ),
        "inliers_all_points": inliers_all,
        "inliers_true_T": inliers_true,
        "inliers_true_T_all_points": inliers_true_all,
        "inlier_fraction": reg.inlier_fraction,
        "overlap": reg.overlap,
        "goal_coverage": reg.goal_coverage,
        "rmse_m": reg.rmse,
        "adds_m": registration_error(world, reg.T, T_goal),
        # the flow's transform point for point (ADD): what the policy's goal flow is off by
        "add_m": registration_add(world, reg.T, T_goal),
        "distance_m": reg.distance,
        "true_distance_m": true_d,
        "verdict_agrees": (reg.distance < SUCCESS_M) == (true_d < SUCCESS_M),
        "verdict": reg.verdict(SUCCESS_M, p.success_margin) if refused is None else "refused",
        "seconds": reg.seconds,
    }


def summarise(rows: list[dict]) -> dict:
    if not rows:
        return {}
    err = np.array([r["adds_m"] for r in rows])
    ok = [r for r in rows if r["refused"] is None]
    return {
        "n": len(rows),
        "refused": sum(r["refused"] is not None for r in rows),
        "widened": sum(r["widened"] for r in rows),
        "refused_all_points_rule": sum(r["refused_all_points_rule"] for r in rows),
        "inliers_all_points_median": float(np.median([r["inliers_all_points"] for r in rows])),
        # with the true transform: what the clouds allow, over the points the goal shows / all points
        "true_T_inliers_median": float(np.median([r["inliers_true_T"] for r in rows])),
        "true_T_inliers_min": float(np.min([r["inliers_true_T"] for r in rows])),
        "true_T_inliers_all_points_median": float(np.median([r["inliers_true_T_all_points"] for r in rows])),
        "true_T_inliers_all_points_min": float(np.min([r["inliers_true_T_all_points"] for r in rows])),
        "inliers_median": float(np.median([r["inlier_fraction"] for r in rows])),
        "overlap_median": float(np.median([r["overlap"] for r in rows])),
        "adds_median_mm": float(np.median(err) * 1000),
        "adds_p90_mm": float(np.quantile(err, 0.9) * 1000),
        "adds_over_1cm": int((err > 0.01).sum()),
        "flow_add_median_mm": float(np.median([r["add_m"] for r in rows]) * 1000),
        "flow_add_over_1cm": int(sum(r["add_m"] > 0.01 for r in rows)),
        "verdict_agrees": float(np.mean([r["verdict_agrees"] for r in ok])) if ok else None,
        # the loop's verdict against the truth
        "false_success": sum(r["verdict"] == "success" and r["true_distance_m"] >= SUCCESS_M for r in ok),
        "false_failure": sum(r["verdict"] == "failure" and r["true_distance_m"] < SUCCESS_M for r in ok),
        "undecided": sum(r["verdict"] in ("ambiguous", "uncertain") for r in ok),
        "distance_error_p90_mm": float(
            np.quantile([abs(r["distance_m"] - r["true_distance_m"]) for r in rows], 0.9) * 1000
        ),
        "distance_error_over_1cm": int(sum(abs(r["distance_m"] - r["true_distance_m"]) > 0.01 for r in rows)),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--goals", choices=("planar", "6d"), default="6d")
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--objects", default="train", help="object set (as `hydo eval --objects`)")
    ap.add_argument("--cell", type=Path, default=None, help="cell YAML (default: the twin's example cell)")
    ap.add_argument("--json", type=Path, help="write results to this JSON file")
    ap.add_argument(
        "--agree-tol",
        type=float,
        default=None,
        help="override robot.registration.AGREE_TOL (the agreement band the registration is picked in)",
    )
    ap.add_argument(
        "--registration",
        choices=("views", "model"),
        default="views",
        help="views: current cloud to goal cloud; model: both through the object's mesh (hydo deploy --registration)",
    )
    args = ap.parse_args()

    t_start = time.time()
    if args.agree_tol is not None:
        registration.AGREE_TOL = args.agree_tol  # read by register() at each call
    cell = load_cell(args.cell)
    assets = load_objects(args.objects)
    world = TwinWorld(cell, seed=args.seed)
    world.load(assets[0])
    rng = np.random.default_rng(args.seed)
    episodes = []
    with open_cameras(cell, "sim", world=world) as cams:
        world.reset_arm()
        world.hide_object()
        background = capture_background(cams, cell, 3)
        for ep in range(args.episodes):
            ep_rng = np.random.default_rng(episode_seed(args.seed, ep))
            asset, start, goal = sample_episode(world, assets, args.goals, ep_rng)
            if world.asset is not asset:
                world.load(asset)
            world.reset_arm()
            T_goal = world.place_object(*goal)
            goal_points = segment(cams.capture(), background, cell, rng).obj_points
            world.place_object(*start)
            tilt = tilt_deg(world.object_T(), T_goal, symmetries(asset))  # as hydo eval splits them
            kind = "flip" if tilt >= FLIP_TILT_DEG else "move"
            row = {"episode": ep, "object": asset.name, "kind": kind}
            model_reg = None
            if args.registration == "model":
                model = ObjectModel.from_asset(asset)
                model_reg = ModelRegistration(model, goal_points, cell.bin_center, cell.cameras, args.goals)
            m = (cell, world, cams, background, T_goal, goal_points, args.goals, ep)
            row["start"] = measure(*m, rng, model_reg)
            if model_reg is not None:  # the goal's own fit (wide search, fitted at the first case)
                row["goal_fit_add_m"] = _goal_fit_add(model_reg, T_goal, cell.bin_center)
            a = rng.uniform(0, 2 * np.pi)
            shift = rng.uniform(*NEAR_SHIFT_M) * np.array([np.cos(a), np.sin(a)])
            pos, quat = np.array(goal[0], float), np.array(goal[1], float)
            pos[:2] += shift
            world.place_object(pos, _quat_yaw(quat, np.deg2rad(rng.uniform(-NEAR_YAW_DEG, NEAR_YAW_DEG))))
            row["near"] = measure(*m, rng, model_reg)
            # its own random stream, so that start and near see the same draws as before it was added
            t_rng = np.random.default_rng([args.seed, ep, 7])
            a = t_rng.uniform(0, 2 * np.pi)
            pos = np.array(goal[0], float)
            pos[:2] += t_rng.uniform(0, TURNED_SHIFT_M) * np.array([np.cos(a), np.sin(a)])
            yaw = t_rng.choice((-1, 1)) * np.deg2rad(t_rng.uniform(*TURNED_YAW_DEG))
            world.place_object(pos, _quat_yaw(quat, yaw))
            row["turned"] = measure(*m, t_rng, model_reg)
            episodes.append(row)
    world.close()

    results: dict = {}
    for case in CASES:
        results[case] = {"all": summarise([e[case] for e in episodes])}
        for kind in ("move", "flip"):
            results[case][kind] = summarise([e[case] for e in episodes if e["kind"] == kind])
    per_object: dict = {}
    for e in episodes:
        o = per_object.setdefault(e["object"], {"n": 0, "refused": 0, "adds_mm": []})
        o["n"] += len(CASES)
        o["refused"] += sum(e[c]["refused"] is not None for c in CASES)
        o["adds_mm"] += [e[c]["adds_m"] * 1000 for c in CASES]
        o["false_success"] = o.get("false_success", 0) + sum(
            e[c]["verdict"] == "success" and e[c]["true_distance_m"] >= SUCCESS_M for c in CASES
        )
    for o in per_object.values():
        o["adds_median_mm"] = float(np.median(o.pop("adds_mm")))

    cols = (
        "n",
        "refused",
        "refused_all_points_rule",
        "inliers_all_points_median",
        "inliers_median",
        "overlap_median",
        "adds_median_mm",
        "adds_p90_mm",
        "adds_over_1cm",
        "flow_add_median_mm",
        "flow_add_over_1cm",
        "distance_error_p90_mm",
        "distance_error_over_1cm",
    )
    print(
        f"registration ({args.registration}) on the twin: {args.goals} goals, {args.episodes} episodes, "
        f"seed {args.seed}"
    )
    verdict_cols = ("verdict_agrees", "false_success", "false_failure", "undecided")
    print(f"{'case':<12}" + "".join(f"{c:>16}" for c in (*cols, *verdict_cols)))
    for case in CASES:
        for kind in ("all", "move", "flip"):
            s = results[case][kind]
            if not s:
                continue
            vals = [s[c] for c in (*cols, *verdict_cols)]
            print(
                f"{case + '/' + kind:<12}"
                + "".join(f"{v:>16.3f}" if isinstance(v, float) else f"{v!s:>16}" for v in vals)
            )
    worst = sorted(per_object.items(), key=lambda kv: -kv[1]["refused"])[:8]
    print(
        "most refused objects: " + ", ".join(f"{k} {v['refused']}/{v['n']}" for k, v in worst if v["refused"])
    )
    fs = sorted(per_object.items(), key=lambda kv: -kv[1]["false_success"])[:8]
    print("false successes: " + ", ".join(f"{k} {v['false_success']}" for k, v in fs if v["false_success"]))
    goal_adds = [e["goal_fit_add_m"] for e in episodes if "goal_fit_add_m" in e]
    if goal_adds:
        results["goal_fit"] = {
            "n": len(goal_adds),
            "add_median_mm": float(np.median(goal_adds) * 1000),
            "add_over_5mm": int(sum(a > 0.005 for a in goal_adds)),
        }
        g = results["goal_fit"]
        print(
            f"goal's model fit: ADD median {g['add_median_mm']:.1f} mm, over 5 mm {g['add_over_5mm']}/{g['n']}"
        )
    wall = time.time() - t_start
    for kind in ("move", "flip"):
        t = results["start"][kind]
        if t:
            print(
                f"start/{kind}, true transform: inliers over the points the goal shows median "
                f"{t['true_T_inliers_median']:.3f} min {t['true_T_inliers_min']:.3f}; over all current points "
                f"median {t['true_T_inliers_all_points_median']:.3f} min {t['true_T_inliers_all_points_min']:.3f}"
            )
    print(f"wall {wall:.0f} s")
    if args.json:
        meta = {
            "command": " ".join(sys.argv),
            "wall_s": wall,
            "python": platform.python_version(),
            "machine": platform.processor() or platform.machine(),
        }
        atomic_write_text(
            args.json,
            json.dumps({**results, "per_object": per_object, "episodes": episodes, "meta": meta}, indent=2),
        )


if __name__ == "__main__":
    main()
