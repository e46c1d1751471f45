"""Data-parallel training on one machine: worker processes that average gradients (torch.distributed,
gloo over loopback TCP).

Why processes and not a collector thread next to a learner: on this 2-core CPU a hydo-cm update takes
~88 % of a serial training step's time and env stepping ~12 % (``bench/trainer.py``), and the update's
cost is linear in the batch (the same ~1,100 samples/s at batch 16, 32 and 64: ``bench/learner.py``),
so overlapping collection with learning could gain at most ~1.14×, and two intra-op torch threads
gained 1.26×. Splitting *both* halves over the cores does better: each worker steps its share of the
envs into its own replay shard and computes the gradient of its half of every batch; the gradients
are averaged before every optimiser step, so all replicas take the same step on the full batch.
"""

from __future__ import annotations

import socket
from datetime import timedelta

import numpy as np
import torch
import torch.distributed as dist


def free_local_address() -> str:
    """``127.0.0.1:PORT`` with a port the OS reports free now (the rendezvous of the workers)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"127.0.0.1:{s.getsockname()[1]}"


class WorkerGroup:
    """One worker's handle on the group: gradient averaging, small all-gathers, barriers.

    ``rank`` 0 is the process that logs, evaluates and writes the checkpoint; ``world`` workers in
    all. Every collective blocks until all workers reach it, so the workers run in lock-step.
    """

    def __init__(self, rank: int, world: int, address: str, timeout_s: float = 1800.0) -> None:
        self.rank, self.world = rank, world
        dist.init_process_group(
            "gloo",
            init_method=f"tcp://{address}",
            rank=rank,
            world_size=world,
            timeout=timedelta(seconds=timeout_s),
        )

    def average_gradients(self, params: list[torch.Tensor]) -> None:
        """Replace each ``p.grad`` by its mean over the workers (one all-reduce of a flat buffer).

        Parameters without a gradient are skipped; which ones have none is the same on every worker
        (the same graph), so the flat buffers line up."""
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return
        flat = torch.cat([g.reshape(-1) for g in grads])
        dist.all_reduce(flat)
        flat /= self.world
        offset = 0
        for g in grads:
            n = g.numel()
            g.copy_(flat[offset : offset + n].view_as(g))
            offset += n

    def gather(self, row: np.ndarray) -> np.ndarray:
        """Every worker's float64 ``row (K,)`` → ``(world, K)``, on every worker."""
        t = torch.from_numpy(np.ascontiguousarray(row, dtype=np.float64))
        out = [torch.empty_like(t) for _ in range(self.world)]
        dist.all_gather(out, t)
        return torch.stack(out).numpy()

    def barrier(self) -> None:
        dist.barrier()

    def close(self) -> None:
        if dist.is_initialized():
            dist.destroy_process_group()
