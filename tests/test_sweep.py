"""``hydo sweep``: methods x seeds as ordinary run folders, locally (a process pool) and on a local Ray
instance through Ray Tune, each with a trial killed mid-run that the sweep resumes from its checkpoint."""

import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest
from typer.testing import CliRunner

from hydo_cli.main import app
from tests.test_cli import hydo
from tests.tiny_run import TINY_AGENT_TOML

runner = CliRunner()
#: A tiny learner and scene (as tests/test_train.py): a trial of a few hundred env steps in seconds.
TINY = (
    """
objects = "cube"
goals = "planar"
steps = 200
n_envs = 2
n_obj = 16
n_bg = 16
batch_size = 8
learning_starts = 16
eval_every = 100
eval_episodes = 2
checkpoint_every = 25
log_every = 25
"""
    + TINY_AGENT_TOML
)
RUN_FILES = ("config.json", "command.txt", "metrics.jsonl", "eval.jsonl", "checkpoint.pt", "replay.npz")


def lines(path):
    return [json.loads(x) for x in path.read_text().splitlines() if x.strip()]


def assert_finished_run(run, algo, seed, steps):
    for name in RUN_FILES:
        assert (run / name).is_file(), (run, name)
    config = json.loads((run / "config.json").read_text())
    assert (config["algo"], config["seed"], config["steps"]) == (algo, seed, steps)
    assert lines(run / "metrics.jsonl")[-1]["env_steps"] >= steps
    assert lines(run / "eval.jsonl")[-1]["env_steps"] >= steps


def kill_when_checkpointed(out, trial, sig=signal.SIGKILL, timeout=240):
    """Kill ``trial``'s training process (pid in DIR/logs/<trial>.pid) once it has a checkpoint and
    before it ends; returns a thread whose ``result`` says at which env step it was killed."""
    result = {}

    def watch():
        run, pid_file = out / trial, out / "logs" / f"{trial}.pid"
        t0 = time.time()
        while time.time() - t0 < timeout:
            if (run / "checkpoint.pt").exists() and pid_file.exists():
                metrics = lines(run / "metrics.jsonl") if (run / "metrics.jsonl").exists() else []
                os.kill(int(pid_file.read_text()), sig)
                result["env_steps"] = metrics[-1]["env_steps"] if metrics else 0
                return
            time.sleep(0.05)

    thread = threading.Thread(target=watch, daemon=True)
    thread.result = result
    thread.start()
    return thread


@pytest.fixture
def tiny(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    return cfg


def test_local_sweep_two_methods_two_seeds_and_resume_after_a_crash(tmp_path, tiny):
    out = tmp_path / "sweep"
    args = ["sweep", "--algos", "hydo-cm,hacman", "--seeds", "0,1", "--config", str(tiny)]
    args += ["--steps", "300", "--out", str(out), "--jobs", "2"]
    # 1. the whole sweep (driver and its trials) is killed while the first trials run
    proc = subprocess.Popen(
        [sys.executable, "-m", "hydo_cli.main", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    run = out / "hydo-cm-s0"
    t0 = time.time()
    while not (run / "checkpoint.pt").exists() and proc.poll() is None and time.time() - t0 < 240:
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGKILL)  # a machine failure: nobody gets to write anything more
    proc.wait()
    killed_at = lines(run / "metrics.jsonl")[-1]["env_steps"]
    assert killed_at < 300, "the trial ended before it could be killed: make TINY slower"
    command_before = (run / "command.txt").read_text()

    # 2. the same command again finishes every trial; the cut one resumes from its checkpoint
    r = hydo(*args)
    assert r.returncode == 0, r.stderr[-3000:]
    for algo in ("hydo-cm", "hacman"):
        for seed in (0, 1):
            assert_finished_run(out / f"{algo}-s{seed}", algo, seed, 300)
    assert (run / "command.txt").read_text() == command_before  # resumed, not started over
    log = (out / "logs" / "hydo-cm-s0.log").read_text()
    assert f"--resume {run}" in log
    state = json.loads((out / "sweep.json").read_text())["trials"]
    assert state["hydo-cm-s0"]["status"] == "done" and state["hydo-cm-s0"]["attempts"] == 2
    assert "hydo eval" in r.stderr and "--compare" in r.stderr and str(out / "hacman-s1") in r.stderr

    # 3. once more: nothing left to run
    r = hydo(*args)
    assert r.returncode == 0 and "0 to run" in r.stderr, r.stderr[-2000:]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--algos", "hydo-cm,ppo"], "unknown method 'ppo'"),
        (["--algos", "hydo-cm", "--seeds", "0,x"], "give comma-separated integers"),
        (["--algos", "hydo-cm,hydo-cm"], "given twice"),
        (["--algos", "hydo-cm", "--config", "nope.toml"], "no such file"),
        (["--algos", "hydo-cm", "--jobs", "0"], "--jobs"),
        (["--algos", "hydo-cm", "--minutes", "-1"], "--minutes must be >= 0"),
    ],
)
def test_sweep_bad_input_is_one_line(tmp_path, args, message):
    r = hydo("sweep", *args, "--out", str(tmp_path / "sweep"))
    assert r.returncode != 0 and message in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_a_failing_trial_fails_the_sweep_in_one_line(tmp_path, tiny):
    out = tmp_path / "sweep"
    r = hydo(
        "sweep", "--algos", "hacman", "--seeds", "0", "--config", str(tiny), "--objects", "no-such-object",
        "--out", str(out),
    )  # fmt: skip
    assert r.returncode != 0 and "1 of 1 trials failed (hacman-s0)" in r.stderr, r.stderr[-2000:]
    assert json.loads((out / "sweep.json").read_text())["trials"]["hacman-s0"]["status"] == "failed"


def test_ray_sweep_resumes_a_killed_trial(tmp_path, tiny):
    ray = pytest.importorskip("ray", reason="the cluster extra (ray[tune]) is not installed")
    pytest.importorskip("ray.tune")
    out = tmp_path / "sweep"
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    try:
        killer = kill_when_checkpointed(out, "hydo-cm-s0")  # a lost node: the process dies mid-run
        r = runner.invoke(
            app,
            ["sweep", "--algos", "hydo-cm", "--seeds", "0,1", "--config", str(tiny), "--steps", "300"]
            + ["--out", str(out), "--ray", "auto", "--max-failures", "2"],
        )
        killer.join(timeout=5)
    finally:
        ray.shutdown()
    assert r.exit_code == 0, r.output[-3000:]
    assert killer.result.get("env_steps", 300) < 300, "the trial ended before it could be killed"
    for seed in (0, 1):
        assert_finished_run(out / f"hydo-cm-s{seed}", "hydo-cm", seed, 300)
    log = (out / "logs" / "hydo-cm-s0.log").read_text()
    assert log.count("[hydo sweep ") == 2 and f"--resume {out / 'hydo-cm-s0'}" in log  # Tune's retry resumed
    assert (out / "logs" / "hydo-cm-s1.log").read_text().count("[hydo sweep ") == 1
    state = json.loads((out / "sweep.json").read_text())["trials"]
    assert all(s["status"] == "done" for s in state.values())


def test_trials_marked_done_at_once_from_two_threads_both_stay_done(tmp_path, monkeypatch):
    """run_local marks trials from its pool threads. A writer that serialised the state before
    another thread's update must not write after it (CI saw a finished trial read back as running)."""
    import hydo_cli.sweep as sweep_mod

    real_write = sweep_mod.atomic_write_text
    first = threading.Event()

    def slow_first_write(path, text):
        if not first.is_set():  # the first writer is slow (a long fsync): the other one overtakes it
            first.set()
            time.sleep(0.3)
        return real_write(path, text)

    monkeypatch.setattr(sweep_mod, "atomic_write_text", slow_first_write)
    trials = [sweep_mod.Trial("hydo-cm", s, tmp_path / f"r{s}", tmp_path / f"r{s}.log") for s in (0, 1)]
    spec = sweep_mod.SweepSpec(tmp_path, trials, [], [], 1)
    a = threading.Thread(target=spec.mark, args=(trials[0], "done"))
    a.start()
    first.wait()
    spec.mark(trials[1], "done")
    a.join()
    state = json.loads((tmp_path / "sweep.json").read_text())["trials"]
    assert {name: t["status"] for name, t in state.items()} == {"hydo-cm-s0": "done", "hydo-cm-s1": "done"}
