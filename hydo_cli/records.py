"""Recorded evaluations: a ``hydo eval --json`` report read back as runs of a new evaluation.

A 150-minute training run fills a 180-minute session, and run folders do not outlive the machine
they were trained on, so a table of several methods x 3 seeds (Table I) is trained one run per
session. Each run is evaluated once, with the table's settings, into ``hydo eval RUN ... --json
FILE`` (gzip it: ``FILE.json.gz``), and the file is kept. ``hydo eval FILE... heuristic --compare``
then lays the table out from the files as if the runs were there: the episodes are the same
(same seed, same episode count, same goal mode), so nothing is rerun, and the IQM and its CI are
taken across the recorded runs as across live ones.

A record is refused, in one line, when it was evaluated on other episodes than this evaluation's
(``--goals``, ``--episodes``, ``--seed``, ``--clutter``, ``--obs``, ``--feasible-only``), lacks one of
its splits, or is not such a report.
"""

from __future__ import annotations

import gzip
import json
from pathlib import Path

from hydo_cli.errors import HydoError
from sim.atomic import atomic_write
from sim.contract import CONTACT_DEFAULT

RECORD_SUFFIXES = (".json", ".json.gz")

#: report keys that fix the episodes and how they were played: a record must match on each
SAME_EPISODES = ("goals", "episodes", "seed", "clutter", "obs", "feasible_only", "contacts")
#: the value of a key that records made before it existed were made with
RECORD_DEFAULTS = {"contacts": CONTACT_DEFAULT}
FLAG = {"feasible_only": "feasible-only"}
#: what the aggregate and the tables read of a run
RUN_KEYS = (
    "target", "method", "objects", "episodes", "episodes_detail", "success_rate", "failures",
    "mean_steps_to_success", "rejected_primitives", "stochastic", "episodes_per_s",
)  # fmt: skip


def is_record(target: str) -> bool:
    """A TARGET naming a recorded evaluation (by its suffix) rather than a policy."""
    return target.endswith(RECORD_SUFFIXES)


def write_report(path: Path, report: dict) -> None:
    """``hydo eval --json PATH``: the report as JSON, gzip-compressed when PATH ends in ``.gz`` (a
    record to keep: ~40 KB for 600 episodes instead of ~300 KB), written atomically."""
    data = json.dumps(report, indent=2).encode()
    if path.name.endswith(".gz"):
        data = gzip.compress(data, mtime=0)  # mtime 0: the same report gives the same bytes
    atomic_write(path, lambda f: f.write(data))


def load_record(path: str) -> dict:
    """The ``hydo eval --json`` report in ``path`` (plain or gzip JSON), checked for the keys used."""
    p = Path(path)
    if not p.is_file():
        raise HydoError(f"recorded evaluation {path} not found")
    try:
        raw = p.read_bytes()
        report = json.loads(gzip.decompress(raw) if path.endswith(".gz") else raw)
    except (OSError, EOFError, ValueError) as e:  # gzip.BadGzipFile and JSONDecodeError are ValueErrors
        raise HydoError(f"{path} is not a readable `hydo eval --json` report ({e})") from None
    if not isinstance(report, dict) or not isinstance(report.get("runs"), list):
        raise HydoError(f"{path} is not a `hydo eval --json` report: it has no list of runs")
    missing = [k for k in (*SAME_EPISODES, "task") if k not in report and k not in RECORD_DEFAULTS]
    if missing:
        raise HydoError(f"{path} is not a `hydo eval --json` report: it lacks {', '.join(missing)}")
    report = {**RECORD_DEFAULTS, **report}
    for run in report["runs"]:
        need = RUN_KEYS
        if not isinstance(run, dict) or any(k not in run for k in need):
            raise HydoError(f"{path}: a run lacks one of {', '.join(need)}")
        if not all(
            isinstance(e, dict) and isinstance(e.get("success"), bool) for e in run["episodes_detail"]
        ):
            raise HydoError(f"{path}: run {run['target']} has an episode without a true/false success")
    return report


def recorded_runs(path: str, report: dict, settings: dict, splits: list[str]) -> dict[str, list[dict]]:
    """The runs of ``report`` (from ``path``) for each of ``splits``: ``{split: [run, ...]}``.

    ``settings`` holds this evaluation's values of :data:`SAME_EPISODES`; a record made with other
    values faced other episodes and is refused. Each run is returned as recorded plus ``recorded:
    path``; its episode count must be this evaluation's.
    """
    if report["task"] is not None:
        raise HydoError(f"{path} is a --task evaluation; records are read for goal evaluations only")
    for key in SAME_EPISODES:
        if report[key] != settings[key]:
            flag = FLAG.get(key, key)
            raise HydoError(
                f"{path} was evaluated with --{flag} {report[key]}, this evaluation with "
                f"--{flag} {settings[key]}: a record is read only for the same episodes"
            )
    out: dict[str, list[dict]] = {}
    for split in splits:
        runs = [r for r in report["runs"] if r["objects"] == split]
        if not runs:
            have = sorted({r["objects"] for r in report["runs"]})
            raise HydoError(f"{path} holds no run on {split} (it has {', '.join(have) or 'none'})")
        for r in runs:
            if len(r["episodes_detail"]) != settings["episodes"]:
                raise HydoError(
                    f"{path}: run {r['target']} on {split} has {len(r['episodes_detail'])} episodes"
                )
        out[split] = [{**r, "recorded": path} for r in runs]
    return out
