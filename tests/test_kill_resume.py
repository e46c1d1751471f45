"""Nothing lost on a crash: a short run SIGKILLed at ≥ 20 random moments (some inside checkpoint
writes) and resumed each time ends where an uninterrupted run with the same seed ends.

What is equal, by design: the env-step and update counters, the set of logged steps in metrics.jsonl
and eval.jsonl (no step repeats, none missing), and one replay transition per env step in the shards
(no duplicates from the dead segments). What differs, and why: episodes in flight at a checkpoint are
restarted on resume (env states are not checkpointed), so the later episodes, the replay's contents
and the weights differ from the uninterrupted run; the work lost per kill is bounded by one checkpoint
interval.
"""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.tiny_run import TINY_AGENT_TOML

ROOT = Path(__file__).resolve().parents[1]
TINY = (
    """
objects = "cube"
goals = "planar"
steps = {steps}
n_envs = 4
n_obj = 32
n_bg = 32
batch_size = 8
buffer_size = 1000
learning_starts = 16
eval_every = 64
eval_episodes = 2
checkpoint_every = 8
log_every = 8
"""
    + TINY_AGENT_TOML
)
STEPS = 400
KILLS = 20


def train(*args: str) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-m", "hydo_cli.main", "train", *args],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )


def logged_steps(run: Path, name: str) -> list[int]:
    return [json.loads(line)["env_steps"] for line in (run / name).read_text().splitlines()]


def replay_size(run: Path) -> int:
    """Transitions in every worker's shard, rebuilt as ``--resume`` rebuilds it (snapshot + segments)."""
    from hydo_cli.trainer import load_shard, read_worker_state, shard_files
    from models.checkpoint import load_checkpoint

    total, rank = 0, 0
    while shard_files(run, rank)[0].exists():
        state_path = shard_files(run, rank)[1]
        state = load_checkpoint(state_path) if rank == 0 else read_worker_state(state_path)
        total += len(load_shard(run, rank, state, 32, 32)[0])
        rank += 1
    return total


@pytest.mark.slow
def test_twenty_sigkills_and_resumes_end_where_an_uninterrupted_run_ends(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY.format(steps=STEPS))
    ref = tmp_path / "reference"
    p = train("--config", str(cfg), "--seed", "5", "--out", str(ref))
    assert p.wait(timeout=600) == 0, p.stderr.read()[-2000:]

    run = tmp_path / "killed"
    rng = np.random.default_rng(0)
    # kill points by progress, not time (a tiny run's speed varies with the machine's load): once the
    # log reaches each of 20 random steps, a random 0-0.3 s later (some land in a checkpoint write)
    targets = np.sort(rng.choice(np.arange(16, STEPS - 80, 8), KILLS, replace=False))
    kills = 0
    for k, target in enumerate(targets):
        p = train(
            *(["--config", str(cfg), "--seed", "5", "--out", str(run)] if k == 0 else ["--resume", str(run)])
        )
        deadline = time.monotonic() + 300
        while p.poll() is None and time.monotonic() < deadline:
            if (
                (run / "metrics.jsonl").exists()
                and (steps := logged_steps(run, "metrics.jsonl"))
                and steps[-1] >= target
            ):
                break
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 0.3))
        assert p.poll() is None, f"the run ended before its kill at step {target}: {p.stderr.read()[-2000:]}"
        os.kill(p.pid, signal.SIGKILL)
        p.wait(timeout=60)
        kills += 1
    while True:  # resume to the end
        p = train("--resume", str(run))
        assert p.wait(timeout=600) == 0, p.stderr.read()[-2000:]
        if logged_steps(run, "metrics.jsonl")[-1] >= STEPS:
            break
    assert kills >= KILLS

    for name in ("metrics.jsonl", "eval.jsonl"):
        steps = logged_steps(run, name)
        assert steps == sorted(set(steps)), f"{name} repeats steps: {steps}"
        assert steps == logged_steps(ref, name), name
    final = [json.loads(line) for line in (run / "metrics.jsonl").read_text().splitlines()][-1]
    final_ref = [json.loads(line) for line in (ref / "metrics.jsonl").read_text().splitlines()][-1]
    assert (final["env_steps"], final["updates"]) == (final_ref["env_steps"], final_ref["updates"])
    assert replay_size(run) == replay_size(ref) == STEPS  # one transition per env step, no duplicates
    # the resumed run is a valid checkpoint for every command
    r = subprocess.run(
        [sys.executable, "-m", "hydo_cli.main", "eval", str(run), "--objects", "cube", "--episodes", "1"],
        cwd=ROOT, capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert r.returncode == 0, r.stderr[-2000:]
