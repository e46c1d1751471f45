"""The old run's decisions on fixed observations, as the code that wrote it (dd74c8e) makes them.

Recorded with that code (never run by the tests):

    git worktree add --detach /tmp/old dd74c8e
    PYTHONPATH=/tmp/old python tests/data/old-run-v0/record_decisions.py /tmp/old \
        tests/data/old-run-v0/decisions-dd74c8e.npz
"""

import sys
from pathlib import Path

import numpy as np
import torch

root, out = Path(sys.argv[1]), Path(sys.argv[2])
sys.path.insert(0, str(root))  # the old code's packages
from hydo_cli.trainer import load_agent  # noqa: E402

agent, cfg, _ = load_agent(Path(__file__).resolve().parent)
rng = np.random.default_rng(20261203)
B, n_obj, n_bg = 4, cfg.n_obj, cfg.n_bg
pts = rng.uniform(-0.2, 0.2, (B, n_obj + n_bg, 3)).astype(np.float32)
pts[:, :n_obj] = pts[:, :n_obj] * 0.2 + np.array([0.05, -0.03, 0.04], np.float32)
feats = np.zeros((B, n_obj + n_bg, 4), np.float32)
feats[:, :n_obj, 0] = 1.0
feats[:, :n_obj, 1:] = rng.normal(0, 0.05, (B, n_obj, 3))
g = torch.Generator().manual_seed(2)
idx, motion, info = agent.act(
    torch.from_numpy(pts), torch.from_numpy(feats), mode="eval", generator=g, feasible_only=False
)
np.savez(
    out,
    points=pts,
    features=feats,
    index=idx.numpy(),
    motion=motion.numpy(),
    q=info["q"].numpy(),
    motions=info["motions"].numpy(),
)
