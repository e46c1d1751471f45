"""Data-parallel workers: two replicas that each take half of a batch and average their gradients
end every update with the weights one agent gets from the whole batch."""

import copy
import threading
import time

import torch
from learner_util import SMALL
from test_algos import make_batch

from models.algos import AgentConfig, HybridAgent
from models.distributed import WorkerGroup, make_group
from models.replay import ReplayBatch


def half(batch: ReplayBatch, k: int) -> ReplayBatch:
    n = batch.reward.shape[0] // 2
    return ReplayBatch(*(None if x is None else x[k * n : (k + 1) * n] for x in batch))


def test_two_workers_on_half_batches_take_the_full_batch_step():
    # TD3 with no target smoothing and the exact actor loss over all points: an update draws no
    # random numbers, so the only difference between the layouts is how the batch is split.
    cfg = AgentConfig(
        algo="hacman", **{**SMALL, "actor_points": None}, target_policy_noise=0.0, policy_delay=1
    )
    single = HybridAgent(cfg)
    workers = [copy.deepcopy(single) for _ in range(2)]
    spec = make_group(2, single.num_parameters() + 2, 4, timeout_s=60)
    groups = [WorkerGroup(rank, spec) for rank in range(2)]
    for agent, group in zip(workers, groups, strict=True):
        agent.sync_gradients = group.average_gradients
    for step in range(3):
        batch = make_batch(8, cfg.n_obj, cfg.n_bg, seed=step)
        single.update(batch)
        threads = [threading.Thread(target=w.update, args=(half(batch, k),)) for k, w in enumerate(workers)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout=60)
    for name in ("encoder", "critic", "motion_policy"):
        ref = getattr(single, name).state_dict()
        for w in workers:
            for key, value in getattr(w, name).state_dict().items():
                torch.testing.assert_close(value, ref[key], rtol=1e-4, atol=1e-5, msg=f"{name}.{key}")
    # the gather collective: every worker sees every row
    rows = [None, None]

    def gather(rank):
        rows[rank] = groups[rank].gather([rank, 10.0 + rank])

    threads = [threading.Thread(target=gather, args=(r,)) for r in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert rows[0].tolist() == rows[1].tolist() == [[0.0, 10.0], [1.0, 11.0]]


def test_a_worker_counts_the_time_it_waits_for_a_late_one():
    spec = make_group(2, 4, 2, timeout_s=60)
    groups = [WorkerGroup(rank, spec) for rank in range(2)]

    def late(rank):
        if rank == 1:
            time.sleep(0.3)  # worker 1 arrives 0.3 s after worker 0
        groups[rank].gather([float(rank)])
        groups[rank].barrier()

    threads = [threading.Thread(target=late, args=(r,)) for r in range(2)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert groups[0].wait_s >= 0.25  # worker 0 sat at the gather's barrier for worker 1
    assert groups[1].wait_s < groups[0].wait_s - 0.2  # the late one hardly waited
