"""Shared fixtures of the deploy tests: a tiny exported model, the example cell, synthetic frames."""

from __future__ import annotations

import numpy as np
import pytest

from robot.cell import load_cell

TINY = dict(feature_dim=16, encoder_hidden=16, encoder_global=16, actor_hidden=16, critic_hidden=16)


def _export_tiny(tmp_path_factory, goals: str, n_checks: int):
    """An untrained hydo-cm policy (cube, 32 + 16 points) exported exactly as ``hydo export`` does."""
    from hydo_cli.config import TrainConfig, agent_config
    from hydo_cli.onnx_export import export_agent
    from models.algos import HybridAgent

    cfg = TrainConfig(algo="hydo-cm", objects="cube", goals=goals, n_obj=32, n_bg=16, agent=TINY)
    out = tmp_path_factory.mktemp(f"deploy-model-{goals}") / "tiny"
    export_agent(
        HybridAgent(agent_config(cfg)), cfg, f"pytest tiny {goals} deploy model", out, n_checks=n_checks
    )
    return out


@pytest.fixture(scope="session")
def tiny_model(tmp_path_factory):
    """The tiny policy for planar goals (most deploy tests)."""
    return _export_tiny(tmp_path_factory, "planar", n_checks=8)


@pytest.fixture(scope="session")
def tiny_model_6d(tmp_path_factory):
    """The tiny policy for 6D goals: its manifest says ``goals = "6d"``."""
    return _export_tiny(tmp_path_factory, "6d", n_checks=2)


@pytest.fixture(scope="session")
def cell():
    return load_cell()


@pytest.fixture
def rng():
    return np.random.default_rng(0)
