"""A run made by an older hydo (tests/data/old-run-v0: a tiny hydo-cm run written before the HL-Gauss
critic, Q-head LayerNorm, EdgeConv and yaw90 options were removed) still loads, resumes its optimiser
state and evaluates exactly as the old code did on the same episodes."""

import json
from pathlib import Path

import numpy as np
import pytest

from hydo_cli.policies import load_agent, load_policy
from hydo_cli.rollout import run_episodes

OLD_RUN = Path(__file__).parent / "data" / "old-run-v0"
# `hydo eval tests/data/old-run-v0 --episodes 6 --seed 2` with the code that wrote the run (commit
# dd74c8e): per-episode return and final distance.
OLD_MEAN_RETURN = -1.6748853512108326
OLD_MEAN_FINAL_DISTANCE_M = 0.19419118079046407


def test_old_config_records_the_removed_options():
    saved = json.loads((OLD_RUN / "config.json").read_text())
    assert saved["augment"] == "none"  # the fixture really is from before the removal
    agent, cfg, _ = load_agent(OLD_RUN)
    assert cfg.algo == "hydo-cm" and agent.n_updates > 0
    # the optimiser state was renumbered past the dropped LayerNorm parameters: one step runs
    params = [p for g in agent.critic_optimizer.param_groups for p in g["params"]]
    assert len(params) == len(list(agent.encoder.parameters())) + len(list(agent.critic.parameters()))
    state = agent.critic_optimizer.state_dict()["state"]
    assert all(state[i]["exp_avg"].shape == p.shape for i, p in enumerate(params) if i in state)


def test_old_run_evaluates_as_before():
    """On the task as the old code defined it: goals as exact poses (``goal_symmetry="none"``; the
    env now asks for goals up to the object's symmetry)."""
    from sim.env import BinEnv

    lp = load_policy(str(OLD_RUN), seed=2)
    envs = [BinEnv(objects="train", goals="planar", n_obj=lp.n_obj, n_bg=lp.n_bg, goal_symmetry="none")]
    results = run_episodes(envs, lp.policy, 6, seed=2)
    assert np.mean([r.episode_return for r in results]) == pytest.approx(OLD_MEAN_RETURN, abs=1e-6)
    assert np.mean([r.final_distance for r in results]) == pytest.approx(OLD_MEAN_FINAL_DISTANCE_M, abs=1e-6)


def test_a_removed_option_that_was_on_is_refused():
    from models.algos import AgentConfig

    with pytest.raises(ValueError, match="critic_bins.*removed"):
        AgentConfig.from_dict({"algo": "hydo", "critic_bins": 64})
