"""Learner tests: one intra-op thread, the allocator setting of training, restored afterwards.

One thread, not two: the tensors here are tiny, and when other work shares the 2-core machine two
OpenMP threads wait on each other at every op (measured: a 1.5 s test took 22 s at load 6).
"""

import pytest
import torch

from models.perf import retain_freed_memory


@pytest.fixture(autouse=True)
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    retain_freed_memory()
    yield
    torch.set_num_threads(threads)
