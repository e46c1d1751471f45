"""What ``hydo eval`` reports: per-run summaries and their aggregation (IQM [95 % CI] per method).

Runs are aggregated within a method only (a method is the run's algo, or a baseline's name): pooling
runs of different methods would mix what Table I compares.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from sim.goals import FLIP_TILT_DEG

#: Table I's columns, in the paper's order.
COMPARE_SPLITS = ("unseen-category", "unseen-instance", "train")
SPLIT_TITLES = {
    "unseen-category": "Unseen Category",
    "unseen-instance": "Unseen Instance",
    "train": "Training Objects",
}
#: A flip that tilts the up direction this much or more turns the object over (a box upside down: two
#: tips, or one push that rolls it); below it, a flip lays the object on a side (one tip).
FLIP_OVER_DEG = 120.0
#: Edges (degrees, up to symmetry) of the JSON's ``by_tilt`` bands: moves; onto a side; 100-150°,
#: mostly cones and the bowl stood up or laid down; upside down (docs/results.md's "by goal tilt").
TILT_BAND_EDGES_DEG = (0.0, FLIP_TILT_DEG, 100.0, 150.0, 180.0)

#: The paper's method names (design.md §1), in Table I's row order; baselines after them.
METHOD_NAMES = {
    "hacman": "HACMan",
    "hacman-diff": "HACMan + Diff",
    "hacman-cm": "HACMan + CM",
    "hydo-gauss": "HyDo (w/o Diff)",
    "hydo": "HyDo",
    "hydo-cm": "HyDo + CM",
    "heuristic": "heuristic",
    "random": "random",
}


# --- the command ---------------------------------------------------------------------------------


def failure_counts(results: Sequence) -> dict[str, int]:
    """Failed episodes by end reason, plus those with at least one refused primitive (overlapping)."""
    failed = [r for r in results if not r.success]
    return {
        "object_left_bin": sum(r.failure == "object_left_bin" for r in failed),
        "timeout": sum(r.failure == "timeout" for r in failed),
        "primitive_rejected": sum(r.rejected > 0 for r in failed),
    }


def run_summary(results: Sequence, task=None) -> dict:
    """Success, steps, failures, per-object breakdown (and behaviour entropy for a task) of one run."""
    from hydo_cli.rollout import summarize

    s = summarize(results)
    per_object: dict[str, list[bool]] = {}
    for r in results:
        per_object.setdefault(r.object, []).append(r.success)
    out = {
        "episodes": s["episodes"],
        "success_rate": s["success_rate"],
        "mean_steps_to_success": s["mean_steps_to_success"],
        "mean_return": s["mean_return"],
        "mean_final_distance_m": s["mean_final_distance_m"],
        "failures": failure_counts(results),
        "rejected_primitives": s["rejected_primitives"],
        "episodes_with_rejected": sum(r.rejected > 0 for r in results),
        # primitives that ran and left the object where it was, and their share of all primitives
        "idle_primitives": int(sum(r.idle for r in results)),
        "idle_share": float(sum(r.idle for r in results) / max(1, sum(r.steps for r in results))),
        "per_object": {
            k: {"episodes": len(v), "success_rate": float(np.mean(v)), **_flip_share(results, k)}
            for k, v in sorted(per_object.items())
        },
        "by_goal": goal_kind_breakdown(results),
        "by_tilt": tilt_bands(results),
    }
    if task is not None:
        from sim.tasks import behaviour_entropy

        ids = behaviour_ids(results)
        counts = np.bincount(ids[ids >= 0], minlength=task.n_behaviours)
        out.update(
            behaviour_entropy=float(behaviour_entropy(ids, task.n_behaviours)),
            behaviours_seen=int((counts > 0).sum()),
            behaviour_counts={str(b): int(n) for b, n in enumerate(counts) if n},
            episodes_without_behaviour=int((ids < 0).sum()),
        )
    return out


def _flip_share(results: Sequence, obj: str) -> dict:
    """``flip_episodes`` and ``flip_success_rate`` of one object's episodes (empty without flips)."""
    flips = [r.success for r in results if r.object == obj and r.goal_tilt_deg >= FLIP_TILT_DEG]
    return {"flip_episodes": len(flips), "flip_success_rate": float(np.mean(flips))} if flips else {}


def tilt_bands(results: Sequence) -> dict[str, dict]:
    """Successes and episodes by the goal's tilt (``goal_tilt_deg``), in the bands between
    ``TILT_BAND_EDGES_DEG`` (keys ``"0-30"``, ``"30-100"``, ...; the last band includes 180°). Every
    band has a row, empty or not, so tables of runs line up."""
    edges = TILT_BAND_EDGES_DEG
    tilt = np.array([r.goal_tilt_deg for r in results], dtype=float)
    success = np.array([r.success for r in results], dtype=bool)
    band = np.clip(np.searchsorted(edges, tilt, side="right") - 1, 0, len(edges) - 2)
    return {
        f"{edges[b]:g}-{edges[b + 1]:g}": {
            "episodes": int((band == b).sum()),
            "successes": int(success[band == b].sum()),
        }
        for b in range(len(edges) - 1)
    }


def goal_kind_breakdown(results: Sequence) -> dict[str, dict]:
    """Success by what the goal asks: ``move`` (same face up: translate and yaw) or ``flip`` (another
    face up, ``goal_tilt_deg`` ≥ FLIP_TILT_DEG), with the episodes' start and final distances (m).
    ``flip`` is split again into ``flip_side`` (tilt under FLIP_OVER_DEG: onto a side) and
    ``flip_over`` (turned over); a kind without episodes has no row. ``force_stops_success`` /
    ``force_stops_failed``: primitives per episode that the hand's contact-force stop ended
    (``sim.primitive.FORCE_STOP_N``), in the kind's successes and failures (None without any): where
    failed flips press harder than the stop allows. ``failed_wrong_face``: the share of the kind's
    failures that end with another face up than the goal's (tilt left ≥ FLIP_TILT_DEG; None without
    failures): for a flip, the object never turned over (it failed to flip, not to place); for a
    move, a push knocked it over. The failures that end on the goal's face (``failed_on_face``, a
    count) are split by what is left (``sim.contract.flow_split``): ``failed_on_face_position_led``, the share of them where placing
    (the centroid's offset) is at least the turning left, and the medians of both, metres
    (``median_failed_on_face_position_m`` / ``_rotation_m``; None without such failures, or in
    records from before the split)."""
    out = {}
    kinds = {
        "move": lambda t: t < FLIP_TILT_DEG,
        "flip": lambda t: t >= FLIP_TILT_DEG,
        "flip_side": lambda t: FLIP_TILT_DEG <= t < FLIP_OVER_DEG,
        "flip_over": lambda t: t >= FLIP_OVER_DEG,
    }
    for kind, is_kind in kinds.items():
        rs = [r for r in results if is_kind(r.goal_tilt_deg)]
        if not rs:
            continue
        failed = [r.final_distance for r in rs if not r.success]
        failed_tilt = [r.final_tilt_deg for r in rs if not r.success]
        on_face = [
            (r.final_position_m, r.final_rotation_m)
            for r in rs
            if not r.success and r.final_tilt_deg < FLIP_TILT_DEG and r.final_position_m is not None
        ]
        pos, rot = np.asarray(on_face, dtype=float).reshape(-1, 2).T
        out[kind] = {
            "episodes": len(rs),
            "success_rate": float(np.mean([r.success for r in rs])),
            "mean_start_distance_m": float(np.mean([r.start_distance for r in rs])),
            "median_failed_final_distance_m": float(np.median(failed)) if failed else None,
            "failed_wrong_face": float(np.mean(np.asarray(failed_tilt) >= FLIP_TILT_DEG)) if failed else None,
            "failed_on_face": sum(not r.success and r.final_tilt_deg < FLIP_TILT_DEG for r in rs),
            "failed_on_face_position_led": float(np.mean(pos >= rot)) if on_face else None,
            "median_failed_on_face_position_m": float(np.median(pos)) if on_face else None,
            "median_failed_on_face_rotation_m": float(np.median(rot)) if on_face else None,
            **{
                f"force_stops_{name}": float(np.mean([r.force_stops for r in group])) if group else None
                for name, group in (
                    ("success", [r for r in rs if r.success]),
                    ("failed", [r for r in rs if not r.success]),
                )
            },
        }
    return out


def behaviour_ids(results: Sequence) -> np.ndarray:
    """Behaviour ids (n,) int, -1 where an episode has none."""
    return np.array([-1 if r.behaviour is None else r.behaviour for r in results], dtype=np.int64)


def method_key(method: str) -> tuple[int, str]:
    order = list(METHOD_NAMES)
    return (order.index(method) if method in order else len(order), method)


# --- aggregation ---------------------------------------------------------------------------------
def aggregate(runs: list[dict], splits: Sequence[str], seed: int, task=None) -> dict:
    """IQM [CI] per method across its runs (strata: splits) and per method and split; entropy for a
    task. ``all`` (and ``behaviour_entropy``) summarise every run only when they are one method's, else
    None: runs of different methods are never pooled."""
    from hydo_cli.stats import interval_estimate

    def successes(run):
        return np.array([e["success"] for e in run["episodes_detail"]], dtype=np.float64)

    def estimate(selected: list[dict], by_split: Sequence[str]) -> dict:
        strata = [[successes(r) for r in selected if r["objects"] == sp] for sp in by_split]
        return interval_estimate(strata, seed=seed).as_dict()

    def entropy_estimate(selected: list[dict]) -> dict:
        from sim.tasks import behaviour_entropy

        def score(ids, axis=-1):
            return behaviour_entropy(np.asarray(ids).astype(np.int64), task.n_behaviours, axis=axis)

        strata = [[behaviour_ids_from_detail(r).astype(np.float64) for r in selected]]
        return interval_estimate(strata, run_score=score, seed=seed, episode_bootstrap=False).as_dict()

    out = {"all": None, "methods": {}}
    methods = sorted({r["method"] for r in runs}, key=method_key)
    for m in methods:
        mine = [r for r in runs if r["method"] == m]
        entry = {
            "name": METHOD_NAMES.get(m, m),
            "targets": sorted({r["target"] for r in mine}, key=[r["target"] for r in mine].index),
            "all": estimate(mine, splits),
            "splits": {sp: estimate(mine, [sp]) for sp in splits},
        }
        if task is not None:
            entry["behaviour_entropy"] = entropy_estimate(mine)
        out["methods"][m] = entry
    if len(methods) == 1:  # across runs only within a method: "all" is that method's
        (only,) = out["methods"].values()
        out["all"] = only["all"]
        if task is not None:
            out["behaviour_entropy"] = only["behaviour_entropy"]
    return out


def behaviour_ids_from_detail(run: dict) -> np.ndarray:
    return np.array(
        [-1 if e["behaviour"] is None else e["behaviour"] for e in run["episodes_detail"]], dtype=np.int64
    )
