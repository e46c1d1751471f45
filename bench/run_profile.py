"""Where a live training run's time goes: py-spy samples of each worker, sorted into the loop's parts.

``bench/trainer.py`` measures the loop alone (no evaluation, no checkpoints, a young replay, a random
policy's pushes); this attaches to a real ``hydo train`` run instead and says, per worker, what share
of its loop went to updates, env steps, waiting for the other worker at the gradient syncs,
evaluation and checkpoints. It only reads the processes (py-spy samples their stacks from outside at
``--rate`` Hz), so a 150-min run can be profiled while it runs without changing what it learns.

Usage::

    python bench/run_profile.py --run runs/6d/hydo-cm-s0 --seconds 90 --json runs/profile.json
    python bench/run_profile.py --raw w0.txt --raw w1.txt --json F   # py-spy ``--format raw`` files

``--run`` finds the processes from the run's ``train.lock`` (worker 0's pid) and its spawned
children (workers 1..). Needs py-spy (``pip install py-spy``; not a dependency of hydo), run with
``--idle`` so that a worker blocked at a barrier is counted as waiting rather than not sampled.

JSON: ``{"meta": {...}, "workers": [{"rank", "pid", "loop_samples", "parts": {part: share},
"env_step": {part: share of the env step}, "update_lines": [{"line", "code", "share"}]}]}``; shares
are fractions of the worker's samples inside its training loop (``Trainer._train``). ``code`` is
that line in this checkout: profile a run trained on other code from a checkout of that code.
"""

from __future__ import annotations

import argparse
import json
import linecache
import platform
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path[:] = [str(ROOT)] + [p for p in sys.path if Path(p or ".").resolve() != ROOT / "bench"]

from sim.atomic import atomic_write_text  # noqa: E402

LOOP = "Trainer._train ("  # a sample counts when the worker is inside its training loop
WAIT = "multiprocessing/synchronize.py"  # blocked at a multiprocessing barrier

# (part, frames that must all be on the stack); the first match names a sample. Order matters: a
# wait inside a checkpoint or a gradient sync is that part's wait, and an evaluation's env steps are
# evaluation.
PARTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("evaluation", ("Trainer._eval_and_log (",)),
    ("checkpoint: waiting", ("Trainer.save (", WAIT)),
    ("checkpoint: writing", ("Trainer.save (",)),
    ("gradient sync: waiting", ("average_gradients (", WAIT)),
    ("gradient sync: copying", ("average_gradients (",)),
    ("stop agreement", ("Trainer._exchange (",)),
    ("update", ("HybridAgent.update (",)),
    ("replay sample", ("ReplayBuffer.sample (",)),
    ("env step", ("BinEnv.step (",)),
    ("env reset", ("BinEnv.reset (",)),
    ("act", ("HybridAgent.act (",)),
)
# Inside an env step (not evaluation's): the push's physics, the settle after it, the observation and
# the reward; the rest is the primitive's planning and checks.
ENV_PARTS: tuple[tuple[str, str], ...] = (
    ("push physics", "BinScene._run_controls ("),
    ("settle", "BinScene.settle ("),
    ("observation", "BinEnv._observe ("),
    ("reward", "BinEnv._evaluate ("),
)


def read_raw(text: str) -> Counter:
    """py-spy ``--format raw`` (one ``frame;frame;... count`` per line) → {stack: samples}."""
    stacks: Counter = Counter()
    for line in text.splitlines():
        stack, _, count = line.rstrip().rpartition(" ")
        if stack and count.isdigit():
            stacks[stack] += int(count)
    return stacks


def part_of(stack: str) -> str:
    for name, frames in PARTS:
        if all(f in stack for f in frames):
            return name
    return "other (loop)"


def _update_line(stack: str) -> str | None:
    """``models/algos.py:N`` of the HybridAgent.update frame: which statement of the update ran."""
    for frame in stack.split(";"):
        if frame.startswith("HybridAgent.update ("):
            return frame[len("HybridAgent.update (") : -1]
    return None


def classify(stacks: Counter) -> dict:
    """Shares of one worker's loop samples by part, of its env steps by env part, and of its updates
    by the update's source line (the 8 largest)."""
    loop = {s: n for s, n in stacks.items() if LOOP in s}
    total = sum(loop.values())
    if total == 0:
        raise SystemExit(
            "error: no samples inside a training loop (Trainer._train): is it a hydo train worker?"
        )
    parts: Counter = Counter()
    env: Counter = Counter()
    lines: Counter = Counter()
    for stack, n in loop.items():
        part = part_of(stack)
        parts[part] += n
        if part == "env step":
            env[next((name for name, f in ENV_PARTS if f in stack), "planning and checks")] += n
        elif part == "update":
            lines[_update_line(stack)] += n
    env_total = sum(env.values()) or 1
    update_lines = []
    for line, n in lines.most_common(8):
        path, _, number = (line or "?:0").rpartition(":")
        code = linecache.getline(str(ROOT / path), int(number) if number.isdigit() else 0).strip()
        update_lines.append({"line": line, "code": code, "share": n / total})
    return {
        "loop_samples": total,
        "parts": {name: parts[name] / total for name, _ in (*PARTS, ("other (loop)", ()))},
        "env_step": {name: n / env_total for name, n in env.most_common()},
        "update_lines": update_lines,
    }


def run_pids(run_dir: Path) -> list[int]:
    """Worker 0's pid (``train.lock``), then its spawned workers' pids in start order."""
    lock = run_dir / "train.lock"
    try:
        pid = int(lock.read_text().split()[1])
    except (OSError, IndexError, ValueError):
        raise SystemExit(f"error: {lock} names no running training process") from None
    children = Path(f"/proc/{pid}/task/{pid}/children")
    if not children.exists():
        raise SystemExit(f"error: the run's process {pid} is not running")
    workers = []
    for child in sorted(int(c) for c in children.read_text().split()):
        try:
            cmd = Path(f"/proc/{child}/cmdline").read_bytes().replace(b"\0", b" ").decode()
        except OSError:
            continue
        if "multiprocessing.spawn" in cmd:  # not the resource tracker
            workers.append(child)
    return [pid, *workers]


def record(pids: list[int], seconds: float, rate: int, out_dir: Path) -> list[Path]:
    """py-spy every pid at once for ``seconds``; the raw files."""
    exe = shutil.which("py-spy") or str(Path(sys.executable).parent / "py-spy")
    if not Path(exe).exists():
        raise SystemExit("error: py-spy is not installed (pip install py-spy)")
    files = [out_dir / f"pyspy-{pid}.txt" for pid in pids]
    procs = [
        subprocess.Popen(
            [exe, "record", "--pid", str(pid), "--rate", str(rate), "--duration", str(int(seconds)), "--idle"]
            + ["--format", "raw", "--output", str(f), "--nonblocking"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        for pid, f in zip(pids, files, strict=True)
    ]
    for pid, p in zip(pids, procs, strict=True):
        _, err = p.communicate()
        if p.returncode != 0:
            raise SystemExit(f"error: py-spy on process {pid} failed: {err.strip().splitlines()[-1:]}")
    return files


def print_table(workers: list[dict]) -> None:
    heads = [f"worker {w['rank']}" for w in workers]
    print(f"{'part of the loop':26s}" + "".join(f"{h:>11s}" for h in heads))
    for name in workers[0]["parts"]:
        print(f"{name:26s}" + "".join(f"{w['parts'][name]:10.1%} " for w in workers))
    print(f"{'samples':26s}" + "".join(f"{w['loop_samples']:10d} " for w in workers))
    for w in workers:
        env = ", ".join(f"{k} {v:.0%}" for k, v in w["env_step"].items())
        print(f"\nworker {w['rank']}: env step = {env}")
        print(f"worker {w['rank']}: update statements (share of the loop):")
        for u in w["update_lines"]:
            print(f"  {u['share']:6.1%}  {u['line']:22s} {u['code'][:80]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    src = ap.add_mutually_exclusive_group(required=True)
    src.add_argument("--run", type=Path, help="a running `hydo train` run directory")
    src.add_argument("--raw", type=Path, action="append", help="py-spy raw output of one worker (repeatable)")
    ap.add_argument("--seconds", type=float, default=60.0, help="sampling time with --run")
    ap.add_argument("--rate", type=int, default=20, help="samples per second with --run")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        pids = run_pids(args.run) if args.run else [None] * len(args.raw)
        files = record(pids, args.seconds, args.rate, Path(tmp)) if args.run else args.raw
        workers = []
        for rank, (pid, f) in enumerate(zip(pids, files, strict=True)):
            try:
                stacks = read_raw(Path(f).read_text())
            except OSError as e:
                raise SystemExit(f"error: cannot read {f}: {e.strerror}") from None
            workers.append({"rank": rank, "pid": pid, **classify(stacks)})
    print_table(workers)
    if args.json:
        meta = {
            "run": str(args.run) if args.run else None,
            "raw": [str(f) for f in args.raw] if args.raw else None,
            "seconds": args.seconds if args.run else None,
            "rate": args.rate if args.run else None,
            "machine": platform.processor() or platform.machine(),
        }
        atomic_write_text(args.json, json.dumps({"meta": meta, "workers": workers}, indent=2))


if __name__ == "__main__":
    main()
