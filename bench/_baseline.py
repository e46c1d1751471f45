"""Another commit's code beside this one, for benches that compare the two in the same session.

Machines of this class differ by ~1.8× in absolute speed (../shared/reference/measurements.md), so a
speed claim is a ratio measured on one machine at one moment: ``bench/trainer.py --baseline REV``
and ``bench/learner.py --baseline REV`` run REV's code (checked out here into a temporary
``git worktree``) and this tree's alternately.
"""

from __future__ import annotations

import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def checkout(rev: str, folder: Path) -> Path:
    """``rev``'s tree in a detached worktree under ``folder`` (removed again by :func:`remove_checkout`)."""
    path = folder / "baseline-src"
    r = subprocess.run(
        ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(path), rev],
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        raise SystemExit(f"bench: cannot check out --baseline {rev}: {r.stderr.strip()}")
    return path


def remove_checkout(path: Path) -> None:
    subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(path)], capture_output=True)
