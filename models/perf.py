"""Process-wide CPU settings for the learner; call :func:`configure_cpu` once at program start.

Why the allocator setting matters: an update allocates and frees a few dozen 1–2 MB activation
tensors. glibc returns freed memory at the top of the heap to the kernel once it exceeds the trim
threshold (and serves large blocks with fresh ``mmap``), so every update faults the same pages back
in: ~6,500 minor page faults and ~24 ms of kernel time per hydo-cm update at batch 32 on the 2-core
machine (``bench/learner.py``). Raising the mmap and trim thresholds keeps freed blocks in the heap
for reuse: the faults drop to ~0 and an update gets ~20–30 % faster. (Preloading tcmalloc has the
same effect; this needs no extra package.) The memory cost is the learner's own peak, held.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import sys

import torch

_M_TRIM_THRESHOLD = -1  # mallopt parameter numbers from glibc's malloc.h
_M_MMAP_THRESHOLD = -3
_applied = False


def retain_freed_memory(mmap_threshold: int = 1 << 30, trim_threshold: int = (1 << 31) - 1) -> bool:
    """Ask glibc's malloc to keep freed memory for reuse (see module docstring).

    Returns True when applied; False on non-glibc platforms (macOS, musl), where it does nothing.
    """
    global _applied
    if not sys.platform.startswith("linux"):
        return False
    name = ctypes.util.find_library("c") or "libc.so.6"
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))
    _applied = _applied or ok
    return ok


def native_bf16() -> str | None:
    """The CPU's native bf16 matrix instructions, from ``/proc/cpuinfo``: "amx_bf16" (Intel Sapphire
    Rapids and later), "avx512_bf16", or None (then torch's bf16 autocast emulates bf16 in fp32
    and is slower: an hydo-cm update ran 10× slower under it on an AMD EPYC Zen 3, docs/experiments.md).
    None off Linux, where the flags cannot be read this way."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line.split(":", 1)[1].split() for line in f if line.startswith("flags")), [])
    except OSError:
        return None
    return next((isa for isa in ("amx_bf16", "avx512_bf16") if isa in flags), None)


PRECISIONS = ("auto", "fp32", "bf16")


def resolve_precision(precision: str) -> str:
    """``"auto" | "fp32" | "bf16"`` → the precision gradient updates run in: "auto" is bf16 autocast
    where the CPU has native bf16 (:func:`native_bf16`) and fp32 elsewhere, where autocast would
    emulate bf16 and run ~10× slower."""
    if precision not in PRECISIONS:
        raise ValueError(f"`precision` must be one of {list(PRECISIONS)}. Got {precision!r}.")
    if precision == "auto":
        return "bf16" if native_bf16() else "fp32"
    return precision


def update_autocast(precision: str) -> contextlib.AbstractContextManager:
    """The context a gradient update runs in for a resolved ``precision``: bf16 autocast runs the
    matmuls (``addmm``, ``baddbmm``) on bf16 inputs with fp32 accumulation; parameters, optimiser
    state, losses and softmaxes stay fp32 (torch's CPU autocast policy). Acting and export are
    always fp32."""
    if precision == "bf16":
        return torch.autocast("cpu", dtype=torch.bfloat16)
    return contextlib.nullcontext()


def configure_cpu(threads: int = 2) -> dict[str, object]:
    """Set torch's intra-op threads, flush-to-zero for denormals and the allocator policy.

    Returns what was set (for run records). Denormal floats (|x| < 1.2e-38, e.g. Adam moments of
    parameters that stopped moving) cost ~100× a normal float op on x86; flushing them to zero
    changes nothing a float32 network can resolve.

    Threads: 2 is fastest on an idle 2-core machine, but when other processes share the cores two
    OpenMP threads wait on each other at every op and an update can get ~10× slower; use 1 there.
    """
    torch.set_num_threads(threads)
    ftz = torch.set_flush_denormal(True)
    return {
        "torch_threads": torch.get_num_threads(),
        "flush_denormal": ftz,
        "malloc_retain": retain_freed_memory(),
    }
