"""The deploy verdict against the twin's truth, re-decided from logged registrations.

Every twin session (``hydo deploy --robot sim``, the ladder's ``twin`` rung) logs, per step, the
registration (distance, goal coverage, inlier fraction, alternatives) and the true distance to the
goal. This bench re-runs ``Registration.verdict`` of the current code on each logged registration
(the cell's success margin, ``--margin``) and counts it against the truth (3 cm):

- per verdict (success / uncertain / ambiguous / failure): how many registrations are truly within
  3 cm and how many are not;
- near the goal (registered distance under 3 cm minus the margin, where a success is claimed):
  how many true and false ones fall under ``SUCCESS_COVERAGE_MIN`` / ``SUCCESS_INLIERS_MIN``, the
  figures those constants rest on;
- per episode, the step where the session stopped on a claim (success, or ambiguous: an ambiguous
  registration or, at the step limit, an uncertain one) and what the current verdict says there.
  A stop it turns ``uncertain`` before the step limit is one the loop would act on again; what
  happens after it is not in the log, so only the stops themselves are counted;
- ``replayed``: the session's success rate had the loop stopped where this verdict first claims
  success (and, with ``--stop-on-ambiguous``, ambiguity: the loop before session 41 ended an
  episode on an ambiguous registration; it now acts again). Up to that step the episode is the logged one (the verdict is the only
  change), so an earlier stop's outcome is the truth at that step; an episode it would carry on past
  the session's own stop is ``unknown``. With ``--success-coverage 0 --success-inliers 0`` this is
  the verdict before those two checks, replayed on a session of the current code: the same episodes,
  the difference the checks make. ``false_success``: the replayed stops that claim a success the
  truth does not back (the verdict's disagreements with the truth, among the failures).

Usage::

    python bench/verdict.py runs/ladder/*/twin --json runs/bench-verdict.json

JSON: ``{"verdicts": {...}, "near_goal": {...}, "stops": {...}, "meta": {...}}``.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from robot import registration  # noqa: E402
from robot.cell import Perception  # noqa: E402
from robot.registration import Registration  # noqa: E402
from robot.session_log import session_folders  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402
from sim.contract import SUCCESS_THRESHOLD_M  # noqa: E402


def _registration(r: dict, folded: bool = False) -> Registration:
    """A logged registration; ``folded``: its session registered to the object's model (logs from
    before the field was written say so only in the session's config)."""
    return Registration(
        np.asarray(r["T"], float),
        r["rmse_m"],
        r["inlier_fraction"],
        r["distance_m"],
        r["seconds"],
        tuple(r["alternative_distances_m"]),
        r["goal_coverage"],
        r["overlap"],
        r.get("folded", folded),
    )


def _events(path: Path) -> list[dict]:
    log = path / "log.jsonl" if path.is_dir() else path
    if not log.is_file():
        raise SystemExit(f"{path}: no log.jsonl (a `hydo deploy --robot sim` session folder)")
    return [json.loads(line) for line in log.read_text().splitlines() if line.strip()]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "sessions",
        nargs="+",
        type=Path,
        help="twin session folders (or their log.jsonl, or a ladder rung's folder of sessions)",
    )
    ap.add_argument("--margin", type=float, default=Perception().success_margin, help="success margin (m)")
    ap.add_argument(
        "--success-coverage",
        type=float,
        default=None,
        help="override robot.registration.SUCCESS_COVERAGE_MIN (0: the verdict without that check)",
    )
    ap.add_argument(
        "--success-inliers",
        type=float,
        default=None,
        help="override robot.registration.SUCCESS_INLIERS_MIN (0: the verdict without that check)",
    )
    ap.add_argument(
        "--stop-on-ambiguous",
        action="store_true",
        help="replay the earlier loop, which ended an episode on an ambiguous registration",
    )
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    claimed = ("success", "ambiguous") if args.stop_on_ambiguous else ("success",)
    if args.success_coverage is not None:  # read by Registration.verdict at each call
        registration.SUCCESS_COVERAGE_MIN = args.success_coverage
    if args.success_inliers is not None:
        registration.SUCCESS_INLIERS_MIN = args.success_inliers

    thr = SUCCESS_THRESHOLD_M
    verdicts: Counter = Counter()  # (verdict, truly within 3 cm)
    near = {"true": [], "false": []}  # (coverage, inliers) of registrations under thr - margin
    stops: Counter = Counter()
    replayed: Counter = Counter()  # success / failure / unknown had the loop stopped on this verdict
    # a ladder rung split over processes holds one session per piece of its episodes
    sessions = [f for path in args.sessions for f in (session_folders(path) or [path])]
    for session in sessions:
        # the session's step limit (a stop there is no claim the verdict could have withheld)
        meta = (session if session.is_dir() else session.parent) / "session.json"
        config = json.loads(meta.read_text())["config"] if meta.is_file() else {}
        limit = config.get("max_steps", 10)
        folded = config.get("registration") == "model"
        obs: dict[int, list[dict]] = {}
        ends: dict[int, dict] = {}
        for e in _events(session):
            if e.get("event") == "observation" and e.get("true_distance_m") is not None:
                obs.setdefault(e["episode"], []).append(e)
            elif e.get("event") == "episode_end":
                ends[e["episode"]] = e
        for ep, steps in obs.items():
            for o in steps:
                reg = _registration(o["registration"], folded)
                truth = o["true_distance_m"] < thr
                verdicts[(reg.verdict(thr, args.margin), truth)] += 1
                if reg.distance < thr - args.margin:
                    near["true" if truth else "false"].append((reg.goal_coverage, reg.inlier_fraction))
            end = ends.get(ep)
            if end is not None:
                claims = [
                    o
                    for o in steps
                    if _registration(o["registration"], folded).verdict(thr, args.margin) in claimed
                ]
                first = claims[0] if claims else None
                if first is not None and first["step"] < steps[-1]["step"]:
                    if first["true_distance_m"] < thr:
                        replayed["success"] += 1
                    else:  # a claim the truth does not back: a false success, a failure by the truth
                        replayed["failure"] += 1
                        replayed["false_success"] += 1
                elif (
                    first is None
                    and end.get("cause") in ("success", "ambiguous")
                    and steps[-1]["step"] < limit
                ):
                    replayed["unknown"] += 1  # it would have acted again where the session stopped
                else:
                    replayed["success" if end.get("true_success") else "failure"] += 1
                    last_claim = _registration(steps[-1]["registration"], folded).verdict(thr, args.margin)
                    if last_claim == "success" and not end.get("true_success"):
                        replayed["false_success"] += 1  # the session's own end, claimed and not true
            if end is not None and end.get("cause") in ("success", "ambiguous"):
                last = steps[-1]
                now = _registration(last["registration"], folded).verdict(thr, args.margin)
                truth = "true" if last["true_distance_m"] < thr else "false"
                stops[f"{end['cause']} ({truth}) -> {now}"] += 1

    def under(rows, cov, inl):
        return {
            "n": len(rows),
            "coverage_under": sum(c < cov for c, _ in rows),
            "inliers_under": sum(i < inl for _, i in rows),
            "either_under": sum(c < cov or i < inl for c, i in rows),
        }

    n_replayed = replayed["success"] + replayed["failure"] + replayed["unknown"]
    cov_min, inl_min = registration.SUCCESS_COVERAGE_MIN, registration.SUCCESS_INLIERS_MIN
    results = {
        "verdicts": {
            v: {"within_3cm": verdicts[(v, True)], "not_within_3cm": verdicts[(v, False)]}
            for v in ("success", "uncertain", "ambiguous", "failure")
        },
        "near_goal": {
            "success_coverage_min": cov_min,
            "success_inliers_min": inl_min,
            "truly_within_3cm": under(near["true"], cov_min, inl_min),
            "not_within_3cm": under(near["false"], cov_min, inl_min),
        },
        "stops": dict(sorted(stops.items())),
        "replayed": {
            **dict(replayed),
            "success_rate": replayed["success"] / max(1, n_replayed),
        },
    }
    print(f"verdict vs truth, {len(sessions)} session(s), margin {args.margin * 1000:.1f} mm")
    print(f"{'verdict':<12}{'within 3 cm':>14}{'not within':>14}")
    for v, c in results["verdicts"].items():
        print(f"{v:<12}{c['within_3cm']:>14}{c['not_within_3cm']:>14}")
    print(
        f"registered under {(thr - args.margin) * 100:.1f} cm: under coverage {cov_min} / inliers {inl_min} / either"
    )
    for k in ("truly_within_3cm", "not_within_3cm"):
        u = results["near_goal"][k]
        print(
            f"  {k:<18} {u['coverage_under']:>4} / {u['inliers_under']:>4} / {u['either_under']:>4} of {u['n']}"
        )
    for k, n in results["stops"].items():
        print(f"stop: {k}: {n}")
    r = results["replayed"]
    print(
        f"replayed with this verdict: success {r['success_rate']:.0%} ({r.get('success', 0)} of "
        f"{n_replayed}; {r.get('unknown', 0)} unknown; {r.get('false_success', 0)} of the failures false successes)"
    )
    if args.json:
        meta = {"command": " ".join(sys.argv), "python": platform.python_version()}
        atomic_write_text(args.json, json.dumps({**results, "meta": meta}, indent=2))


if __name__ == "__main__":
    main()
