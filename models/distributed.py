"""Data-parallel training on one machine: worker processes that average gradients through shared
memory.

Why processes and not a collector thread next to a learner: on this 2-core CPU a hydo-cm update takes
~88 % of a serial training step's time and env stepping ~12 %, and the update's cost is linear in
the batch (the same ~1,100 samples/s at batch 16, 32 and 64: ``bench/learner.py``), so overlapping
collection with learning could gain at most ~1.14×, and two intra-op torch threads gained 1.26×.
Splitting *both* halves over the cores does better: each worker steps its share of the envs into its
own replay shard and computes the gradient of its share of every batch; the gradients are averaged
before every optimiser step, so all replicas take the same step on the full batch.

Why shared memory and not ``torch.distributed``: the workers share one machine, and an update syncs
its gradients one to two times. In a two-process microbenchmark (not kept), gloo over loopback TCP
took ~1.3 ms per all-reduce of the ~60k gradients; a write into a shared tensor, one
``multiprocessing.Barrier`` and a sum took ~0.3 ms.
"""

from __future__ import annotations

import multiprocessing
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch


@dataclass
class GroupSpec:
    """What every worker needs to join the group; passed to spawned workers as a process argument
    (torch shares the tensors' memory, ``multiprocessing`` the barrier)."""

    world: int
    barrier: Any  # multiprocessing.Barrier(world)
    grads: torch.Tensor  # (2, world, n_grads) float32: double-buffered gradient slots
    rows: torch.Tensor  # (2, world, row_size) float64: double-buffered gather slots


def make_group(world: int, n_grads: int, row_size: int, timeout_s: float = 1800.0) -> GroupSpec:
    """The shared state of a group of ``world`` workers whose largest gradient sync has
    ``n_grads`` elements and whose gathers have at most ``row_size`` numbers (call in worker 0
    before spawning the others with the ``spawn`` context)."""
    ctx = multiprocessing.get_context("spawn")
    return GroupSpec(
        world=world,
        barrier=ctx.Barrier(world, timeout=timeout_s),
        grads=torch.zeros(2, world, n_grads, dtype=torch.float32).share_memory_(),
        rows=torch.zeros(2, world, row_size, dtype=torch.float64).share_memory_(),
    )


class WorkerGroup:
    """One worker's handle on the group: gradient averaging, small all-gathers, barriers.

    ``rank`` 0 is the worker that logs, evaluates and writes the checkpoint. Every collective is one
    barrier crossing, so the workers run in lock-step. Each kind of slot is double-buffered: a worker
    writes slot ``k % 2`` and reads every worker's after the barrier; the same slot is written again
    only two collectives later, after a barrier that every reader has passed.
    """

    def __init__(self, rank: int, spec: GroupSpec) -> None:
        self.rank, self.world, self.spec = rank, spec.world, spec
        self._k_grads = 0
        self._k_rows = 0
        #: Seconds this worker has spent waiting at the group's barriers: the lock-step's idle time
        #: (the faster worker waits there for the slower one's env steps or evaluation).
        self.wait_s = 0.0

    def _wait(self) -> None:
        t = time.perf_counter()
        self.spec.barrier.wait()
        self.wait_s += time.perf_counter() - t

    def average_gradients(self, params: list[torch.Tensor]) -> None:
        """Replace each ``p.grad`` by its mean over the workers.

        Parameters without a gradient are skipped; which ones have none is the same on every worker
        (the same graph), so the flat buffers line up."""
        grads = [p.grad for p in params if p.grad is not None]
        if not grads:
            return
        n = sum(g.numel() for g in grads)
        slots = self.spec.grads[self._k_grads % 2]  # (world, n_grads)
        self._k_grads += 1
        torch.cat([g.reshape(-1) for g in grads], out=slots[self.rank, :n])
        self._wait()
        mean = slots[:, :n].sum(0) / self.world
        offset = 0
        for g in grads:
            g.copy_(mean[offset : offset + g.numel()].view_as(g))
            offset += g.numel()

    def gather(self, row: np.ndarray) -> np.ndarray:
        """Every worker's ``row (K,)`` → ``(world, K)`` float64, on every worker."""
        k = len(row)
        slots = self.spec.rows[self._k_rows % 2]  # (world, row_size)
        self._k_rows += 1
        slots[self.rank, :k] = torch.from_numpy(np.asarray(row, dtype=np.float64))
        self._wait()
        return slots[:, :k].numpy().copy()

    def barrier(self) -> None:
        self._wait()

    def abort(self) -> None:
        """On failure: break the barrier, so a worker waiting at it stops instead of hanging."""
        self.spec.barrier.abort()
