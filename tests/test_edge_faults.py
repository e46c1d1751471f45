"""Faults at the edges (issue 30): read-only output folders, two ``hydo train --resume`` on one run at
once, SIGINT / SIGTERM during ``hydo eval --json``, and paths with spaces and non-ASCII characters.
Each runs the real CLI as a subprocess; a refusal is one stderr line, exit 1, no traceback."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
OLD_RUN = ROOT / "tests" / "data" / "old-run-v0"
MODEL = ROOT / "models" / "hydo-cm-planar"


def popen(args: list, cwd: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    env.pop("HYDO_DEBUG", None)
    return subprocess.Popen(
        [sys.executable, "-m", "hydo_cli.main", *map(str, args)],
        cwd=cwd,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        # a shell's background job starts with SIGINT ignored, and a child would inherit that (Python
        # then never raises KeyboardInterrupt): give it the default, as a terminal's Ctrl-C finds it
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )


def hydo(args: list, cwd: Path) -> tuple[int, str]:
    p = popen(args, cwd)
    _, err = p.communicate(timeout=300)
    return p.returncode, err


def assert_one_line(code: int, err: str, *words: str) -> None:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 1 and "Traceback" not in err and len(lines) == 1, (code, err[-2000:])
    assert lines[0].startswith("hydo: error: ") and all(w in lines[0] for w in words), err


# --- read-only output folders -----------------------------------------------------------------------------


def read_only_folders(tmp_path: Path) -> list[Path]:
    """Folders this process cannot write: /proc/sys takes no new files even from root (CI runs as
    root, where chmod stops nothing), and, for other users, a folder chmod 0555 as well."""
    folders = [Path("/proc/sys")]
    if os.geteuid() != 0:
        ro = tmp_path / "read only ü"
        ro.mkdir()
        ro.chmod(0o555)
        folders.append(ro)
    return folders


@pytest.mark.parametrize("command", ["train", "eval", "export"])
def test_read_only_output(command, tmp_path):
    for folder in read_only_folders(tmp_path):
        args = {
            "train": ["train", "--preset", "quick", "--out", folder / "run"],
            "eval": [
                "eval",
                "heuristic",
                "--objects",
                "cube",
                "--episodes",
                "1",
                "--json",
                folder / "e.json",
            ],
            "export": ["export", OLD_RUN, "--out", folder / "model"],
        }[command]
        code, err = hydo(args, tmp_path)
        assert_one_line(code, err, "not writable", str(folder))


# --- two resumes of one run ------------------------------------------------------------------------------


def test_second_resume_is_refused_by_the_lock(tmp_path):
    run = tmp_path / "run with spaces ü"
    shutil.copytree(OLD_RUN, run)
    first = popen(["train", "--resume", run, "--steps", "100000", "--fresh-replay"], tmp_path)
    try:
        lock = run / "train.lock"
        t0 = time.time()
        while not (lock.exists() and lock.read_text().startswith("pid")) and time.time() - t0 < 120:
            assert first.poll() is None, first.communicate()[1][-2000:]
            time.sleep(0.2)
        assert lock.read_text().strip() == f"pid {first.pid}"
        code, err = hydo(["train", "--resume", run], tmp_path)
        assert_one_line(code, err, "being trained by another", str(run), f"pid {first.pid}")
    finally:
        first.send_signal(signal.SIGTERM)  # the trainer checkpoints and exits
        first.communicate(timeout=120)
    # the lock went with the first process: the run resumes again
    code, err = hydo(["train", "--resume", run, "--minutes", "0.001", "--fresh-replay"], tmp_path)
    assert code == 0, err[-2000:]


# --- a signal during eval --json ------------------------------------------------------------------------


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_signal_during_eval_leaves_no_half_written_json(sig, tmp_path):
    out = tmp_path / "out dir ü" / "results ü.json"
    p = popen(["eval", "heuristic", "--objects", "cube", "--episodes", "100000", "--json", out], tmp_path)
    time.sleep(10)  # imports done, episodes running (nothing is printed before the summary)
    assert p.poll() is None, p.communicate()[1][-2000:]
    p.send_signal(sig)
    try:
        _, err = p.communicate(timeout=120)
    finally:
        p.kill()  # never leave it running if it ignored the signal
    assert p.returncode != 0 and "Traceback" not in err, (p.returncode, err[-2000:])
    assert not out.exists()
    strays = [f for f in tmp_path.rglob("*") if f.is_file()]
    assert strays == [], strays  # no torn file and no temporary beside it


# --- paths with spaces and non-ASCII characters ----------------------------------------------------------


def test_unicode_paths_end_to_end(tmp_path):
    """A model, a cell and a result file whose paths hold spaces and non-ASCII characters work."""
    folder = tmp_path / "modèles et résultats"
    model = folder / "hydo cm ü"
    shutil.copytree(MODEL, model)
    cell = folder / "céllule 1.yaml"
    shutil.copy(ROOT / "robot" / "cell.example.yaml", cell)
    out = folder / "éval ü.json"
    code, err = hydo(["eval", model, "--episodes", "1", "--json", out], tmp_path)
    assert code == 0 and out.is_file(), err[-2000:]
    code, err = hydo(
        [
            "deploy",
            "--robot",
            "sim",
            "--model",
            model,
            "--cell",
            cell,
            "--dry-run",
            "--log",
            folder / "séance",
        ],
        tmp_path,
    )
    assert code == 0, err[-2000:]
