"""`hydo train` end to end: a tiny run writes its record, resumes where it stopped, and its result is
usable by `hydo eval` and `hydo export`."""

import json

import pytest

from tests.test_cli import hydo
from tests.tiny_run import TINY_AGENT_TOML

TINY = (
    """
objects = "cube"
goals = "planar"
steps = 48
n_envs = 4
n_obj = 32
n_bg = 32
batch_size = 8
learning_starts = 16
eval_every = 24
eval_episodes = 2
checkpoint_every = 24
log_every = 8
threads = 1
"""
    + TINY_AGENT_TOML
)


def _lines(path):
    return [json.loads(x) for x in path.read_text().splitlines()]


def test_train_resume_eval_export(tmp_path):
    cfg = tmp_path / "tiny.toml"
    cfg.write_text(TINY)
    run = tmp_path / "run"
    r = hydo("train", "--config", str(cfg), "--algo", "hydo-cm", "--seed", "3", "--out", str(run))
    assert r.returncode == 0, r.stderr[-2000:]
    for name in (
        "config.json",
        "command.txt",
        "system.json",
        "metrics.jsonl",
        "eval.jsonl",
        "checkpoint.pt",
        "replay.npz",
    ):
        assert (run / name).is_file(), name
    config = json.loads((run / "config.json").read_text())
    assert config["algo"] == "hydo-cm" and config["seed"] == 3 and config["agent"]["feature_dim"] == 16
    assert json.loads((run / "system.json").read_text())["torch_threads"] == 1
    metrics = _lines(run / "metrics.jsonl")
    assert metrics[-1]["env_steps"] >= 48 and metrics[-1]["updates"] > 0
    assert "peak_rss_mb" in metrics[-1]
    # two workers (the default): each row says what share of its interval they waited at the syncs
    assert metrics[-1]["workers"] == 2
    assert all(0.0 <= m["sync_wait_share"] <= 1.0 for m in metrics)
    evals = _lines(run / "eval.jsonl")
    assert [e["env_steps"] for e in evals][:2] == [24, 48] and all(e["episodes"] == 2 for e in evals)
    # both workers played one of the 2 episodes; the row pools them and says how long it took
    assert all(e["eval_s"] > 0 for e in evals)
    # TensorBoard mirror (tensorboard is in the test extra): the eval success rate per evaluation
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    events = EventAccumulator(str(run / "tensorboard"))
    events.Reload()
    assert [e.step for e in events.Scalars("eval/success_rate")][:2] == [24, 48]

    # a second invocation without --resume refuses to overwrite the run
    r = hydo("train", "--config", str(cfg), "--out", str(run))
    assert r.returncode != 0 and "already holds a run" in r.stderr

    # --resume continues the step and update counters (and extends with --steps)
    updates_before = metrics[-1]["updates"]
    r = hydo("train", "--resume", str(run), "--steps", "72")
    assert r.returncode == 0, r.stderr[-2000:]
    metrics = _lines(run / "metrics.jsonl")
    assert metrics[-1]["env_steps"] >= 72 and metrics[-1]["updates"] > updates_before
    assert [e["env_steps"] for e in _lines(run / "eval.jsonl")][-1] >= 72

    # the run is a valid eval target and exports
    out = tmp_path / "eval.json"
    r = hydo("eval", str(run), "--objects", "cube", "--episodes", "2", "--json", str(out))
    assert r.returncode == 0, r.stderr[-2000:]
    detail = json.loads(out.read_text())["runs"][0]["episodes_detail"]
    assert len(detail) == 2
    assert json.loads(out.read_text())["runs"][0]["success_rate"] == sum(e["success"] for e in detail) / 2
    assert json.loads(out.read_text())["runs"][0]["stochastic"] is True  # the cm chain samples
    r = hydo(
        "eval", str(run), "--objects", "cube", "--episodes", "1", "--chain-noise", "zero", "--json", str(out)
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert json.loads(out.read_text())["runs"][0]["stochastic"] is False
    assert json.loads(out.read_text())["chain_noise"] == "zero"
    r = hydo("export", str(run), "--out", str(tmp_path / "model"))
    assert r.returncode == 0, r.stderr[-2000:]
    assert (tmp_path / "model" / "manifest.json").is_file()


def test_every_shipped_config_resolves():
    """configs/**/*.toml: every key is a TrainConfig field and every [agent] key an AgentConfig field."""
    from pathlib import Path

    from hydo_cli.config import agent_config, resolve_config

    root = Path(__file__).resolve().parents[1] / "configs"
    files = sorted(root.rglob("*.toml"))
    assert len(files) >= 5  # the planar, 6d and task configs
    for path in files:
        cfg = resolve_config(None, path, {"algo": "hydo-cm"})
        agent_config(cfg)  # raises on an unknown or invalid agent field


def test_replay_is_checkpointed_as_a_snapshot_and_segments(tmp_path):
    """With a small replay and frequent checkpoints, a run writes a snapshot and then segments of what
    each interval added (a new snapshot once they hold a shard's capacity), keeps only the files its
    last checkpoint needs, and resumes from them on both workers."""
    import numpy as np
    import torch

    cfg = tmp_path / "tiny.toml"
    cfg.write_text(
        TINY.replace("checkpoint_every = 24", "checkpoint_every = 4").replace(
            "threads = 1\n", "threads = 1\nbuffer_size = 32\n"
        )
    )
    run = tmp_path / "run"
    r = hydo("train", "--config", str(cfg), "--seed", "1", "--steps", "40", "--out", str(run))
    assert r.returncode == 0, r.stderr[-2000:]

    def replay_files(stem):
        return sorted(p.name for p in run.glob(f"{stem}.s*.npz"))

    ckpt = torch.load(run / "checkpoint.pt", weights_only=True)["payload"]
    worker = torch.load(run / "worker-1.pt", weights_only=True)["payload"]
    for stem, state in (("replay", ckpt), ("replay-1", worker)):
        with np.load(run / f"{stem}.npz") as z:
            snap = int(z["seq"])
        # 10 checkpoints of 4 env steps + the final one; a shard holds 16, each checkpoint adds 2
        assert state["replay_seq"] == 11 and 1 < snap < state["replay_seq"]
        assert replay_files(stem) == [
            f"{stem}.s{k:05d}.npz" for k in range(snap + 1, state["replay_seq"] + 1)
        ]
        assert 0 <= state["replay_logged"] <= 16

    r = hydo("train", "--resume", str(run), "--steps", "56")
    assert r.returncode == 0, r.stderr[-2000:]
    assert _lines(run / "metrics.jsonl")[-1]["env_steps"] >= 56
    assert torch.load(run / "checkpoint.pt", weights_only=True)["payload"]["replay_seq"] > 11

    # a segment the checkpoint needs is gone: --resume names it and refuses (worker 1 is checked first)
    worker = torch.load(run / "worker-1.pt", weights_only=True)["payload"]
    with np.load(run / "replay-1.npz") as z:
        snap = int(z["seq"])
    assert worker["replay_seq"] > snap
    (run / f"replay-1.s{worker['replay_seq']:05d}.npz").unlink()
    r = hydo("train", "--resume", str(run), "--steps", "64")
    assert r.returncode == 1 and "replay-1.s" in r.stderr and "is missing" in r.stderr
    assert "Traceback" not in r.stderr


def test_flip_share_is_refused_for_planar_goals_in_one_line():
    from hydo_cli.config import TrainConfig
    from hydo_cli.errors import HydoError

    assert TrainConfig.parse({"goals": "6d", "flip_share": 0.7}, "run.toml").flip_share == 0.7
    with pytest.raises(HydoError, match=r"run\.toml.*flip_share.*6d") as e:
        TrainConfig.parse({"goals": "planar", "flip_share": 0.7}, "run.toml")
    assert "\n" not in str(e.value)


def test_contacts_are_a_training_key_checked_in_one_line():
    from hydo_cli.config import TrainConfig
    from hydo_cli.errors import HydoError

    assert TrainConfig.parse({}, "run.toml").contacts == "hydo"  # old configs: the scene's own
    assert TrainConfig.parse({"contacts": "hacman"}, "run.toml").contacts == "hacman"
    with pytest.raises(HydoError, match=r"run\.toml.*contacts") as e:
        TrainConfig.parse({"contacts": "robosuite"}, "run.toml")
    assert "\n" not in str(e.value)


def test_an_evaluation_during_training_does_not_splice_episodes(tmp_path):
    """Evaluations run on the training envs. Every pair of stored transitions the replay links as one
    episode (``next_slot``: hindsight goals, n-step returns) must continue it: the same cloud and
    the same goal. An episode that an evaluation interrupted is ended, not continued in a state the
    evaluation left behind."""
    import numpy as np

    cfg = TINY.replace("eval_every = 24", "eval_every = 8").replace("eval_episodes = 2", "eval_episodes = 4")
    cfg = cfg.replace("learning_starts = 16", "learning_starts = 48").replace(
        "threads = 1\n", "threads = 1\nworkers = 1\n"
    )
    path = tmp_path / "tiny.toml"
    path.write_text(cfg)
    run = tmp_path / "run"
    r = hydo("train", "--config", str(path), "--seed", "2", "--out", str(run))
    assert r.returncode == 0, r.stderr[-2000:]
    with np.load(run / "replay.npz") as z:
        nxt, goal, next_goal = z["next_slot"], z["goal_T"], z["next_goal_T"]
        points, next_points = z["points"], z["next_points"]
    linked = np.flatnonzero(nxt >= 0)
    assert len(linked) > 10
    for prev in linked:
        np.testing.assert_array_equal(next_points[prev], points[nxt[prev]])
        np.testing.assert_allclose(next_goal[prev], goal[nxt[prev]], atol=1e-6, err_msg=f"slot {prev}")
