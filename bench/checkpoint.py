"""What a training checkpoint costs in replay writes: a whole shard against one interval's segment.

A run checkpoints every ``checkpoint_every`` env steps; each of its ``workers`` writes its replay
shard. Before segments, every checkpoint rewrote the whole shard (``ReplayBuffer.save``); now it
writes what the interval added (``ReplayBuffer.save_segment``) and a whole snapshot only once the
segments since the last one hold a shard's capacity. This fills one shard at the 6D run's sizes
(``buffer_size / workers`` transitions at 128 + 128 points), then times, on this machine's disk
(written atomically with fsync, as the trainer does):

- ``snapshot_s``: one whole-shard write (what every checkpoint cost before);
- ``segment_s``: one segment of ``checkpoint_every / workers`` transitions;
- ``rebuild_s``: loading the snapshot and applying ``--segments`` segments (what ``--resume`` does);
- ``mean_write_s_per_checkpoint``: a full shard's writes averaged over the snapshot cycle
  (one snapshot per ``capacity / interval`` checkpoints).

Prints a table; ``--json FILE`` writes the figures::

    python bench/checkpoint.py --json out/checkpoint.json
    python bench/checkpoint.py --capacity 20000 --interval 1250     # a smaller shard
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402

from models.checkpoint import apply_replay_segment, load_replay  # noqa: E402
from models.replay import ReplayBuffer  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402


def fill(buf: ReplayBuffer, rng: np.random.Generator) -> None:
    """Every slot with float16 clouds of the contract's scale (contents do not change write cost)."""
    for name in ("points", "next_points", "features", "next_features", "normals", "next_normals"):
        a = getattr(buf, name)
        a[...] = rng.normal(0, 0.1, a.shape).astype(a.dtype)
    buf.index[:] = rng.integers(0, buf.n_obj, buf.capacity)
    buf.motion[:] = rng.uniform(-1, 1, buf.motion.shape)
    buf.pos, buf.full = 0, True


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capacity", type=int, default=100_000, help="transitions per shard (6D: 200k / 2)")
    ap.add_argument("--interval", type=int, default=1_250, help="transitions a shard adds per checkpoint")
    ap.add_argument("--segments", type=int, default=8, help="segments applied in the rebuild timing")
    ap.add_argument("--n-obj", type=int, default=128)
    ap.add_argument("--n-bg", type=int, default=128)
    ap.add_argument("--dir", type=Path, default=None, help="folder to write in (default: a temp folder)")
    ap.add_argument("--json", type=Path, help="write the results here")
    args = ap.parse_args()
    if not 0 < args.interval <= args.capacity or args.segments < 1:
        raise SystemExit("bench/checkpoint.py: need 0 < --interval <= --capacity and --segments >= 1")

    rng = np.random.default_rng(0)
    buf = ReplayBuffer(args.capacity, args.n_obj, args.n_bg, seed=0)
    fill(buf, rng)
    with tempfile.TemporaryDirectory(prefix="hydo-bench-ckpt-", dir=args.dir) as tmp:
        folder = Path(tmp)
        t0 = time.perf_counter()
        buf.save(folder / "replay.npz", seq=1)
        snapshot_s = time.perf_counter() - t0
        segment_times = []
        for k in range(args.segments):
            buf.unsaved = args.interval  # as if the interval's transitions had just been added
            buf.pos = (buf.pos + args.interval) % buf.capacity
            t0 = time.perf_counter()
            buf.save_segment(folder / f"replay.s{k + 2:05d}.npz")
            segment_times.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        back = load_replay(folder / "replay.npz", args.n_obj, args.n_bg)
        for k in range(args.segments):
            apply_replay_segment(back, folder / f"replay.s{k + 2:05d}.npz")
        rebuild_s = time.perf_counter() - t0
        assert back.pos == buf.pos and np.array_equal(back.points[:64], buf.points[:64])
    segment_s = float(np.median(segment_times))
    cycle = max(1, args.capacity // args.interval)  # checkpoints per snapshot
    mean_write = (snapshot_s + (cycle - 1) * segment_s) / cycle
    results = {
        "snapshot_s": snapshot_s,
        "segment_s": segment_s,
        "rebuild_s": rebuild_s,
        "mean_write_s_per_checkpoint": mean_write,
        "write_speedup": snapshot_s / mean_write,
        "shard_mb": buf.nbytes / 1e6,
        "segment_mb": args.interval * buf.bytes_per_transition / 1e6,
        "meta": {**vars(args), "dir": str(args.dir), "json": str(args.json), "platform": platform.platform()},
    }

    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"replay checkpoint writes, one shard of {args.capacity:,} transitions")
    for col in ("what", "MB", "seconds"):
        table.add_column(col, justify="right")
    table.add_row("whole shard (every checkpoint before)", f"{results['shard_mb']:.0f}", f"{snapshot_s:.2f}")
    table.add_row(f"segment of {args.interval:,}", f"{results['segment_mb']:.1f}", f"{segment_s:.3f}")
    table.add_row(f"mean per checkpoint (1 snapshot per {cycle})", "", f"{mean_write:.3f}")
    table.add_row(f"rebuild: snapshot + {args.segments} segments", "", f"{rebuild_s:.2f}")
    Console().print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
