"""hydo learners, torch only: encoder, motion policies, critics, the six algorithms, replay, checkpoints.

Tensors in, tensors out: nothing here imports ``sim`` or ``robot``. Start at ``models.algos``.
"""

from models.algos import ALGOS, AgentConfig, AlgoSpec, HybridAgent
from models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from models.replay import ReplayBatch, ReplayBuffer

__all__ = [
    "ALGOS",
    "AgentConfig",
    "AlgoSpec",
    "CheckpointError",
    "HybridAgent",
    "ReplayBatch",
    "ReplayBuffer",
    "load_checkpoint",
    "save_checkpoint",
]
