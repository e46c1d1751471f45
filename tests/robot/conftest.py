"""Shared fixtures of the deploy tests: a tiny exported model, the example cell, synthetic frames."""

from __future__ import annotations

import numpy as np
import pytest

from robot.cell import load_cell

TINY = dict(feature_dim=16, encoder_hidden=16, encoder_global=16, actor_hidden=16, critic_hidden=16)


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory):
    """An untrained hydo-cm policy (planar goals, cube) exported exactly as ``hydo export`` does."""
    from hydo_cli.config import TrainConfig, agent_config
    from hydo_cli.onnx_export import export_agent
    from models.algos import HybridAgent

    cfg = TrainConfig(algo="hydo-cm", objects="cube", goals="planar", n_obj=32, n_bg=16, agent=TINY)
    out = tmp_path_factory.mktemp("deploy-model") / "tiny"
    export_agent(HybridAgent(agent_config(cfg)), cfg, "pytest tiny deploy model", out, n_checks=8)
    return out


@pytest.fixture(scope="session")
def tiny_model_6d(tmp_path_factory):
    """``tiny_model`` trained (untrained) for 6D goals: its manifest says ``goals = "6d"``."""
    from hydo_cli.config import TrainConfig, agent_config
    from hydo_cli.onnx_export import export_agent
    from models.algos import HybridAgent

    cfg = TrainConfig(algo="hydo-cm", objects="cube", goals="6d", n_obj=32, n_bg=16, agent=TINY)
    out = tmp_path_factory.mktemp("deploy-model-6d") / "tiny"
    export_agent(HybridAgent(agent_config(cfg)), cfg, "pytest tiny 6D deploy model", out, n_checks=2)
    return out


@pytest.fixture(scope="session")
def cell():
    return load_cell()


@pytest.fixture
def rng():
    return np.random.default_rng(0)
