"""One decision (encoder + K-step actor over all object points + twin critic + location choice):
torch eager vs onnxruntime, in one process, at the default point counts.

    python bench/inference.py [--algo hydo-cm] [--runs 300] [--json FILE] [--run runs/NAME]

The agent (a fresh one of ``--algo``, or the trained one in ``--run``; timings do not depend on the
weights) is exported to a temp folder, then both engines decide on the same observations. Prints a table and, with ``--json``, writes ``ort_ms_median``,
``torch_ms_median``, p90s, per-graph onnxruntime times and ``meta``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # bench/ must not shadow the packages

import numpy as np  # noqa: E402
import torch  # noqa: E402


def _stats(ms: list[float]) -> tuple[float, float]:
    return float(np.median(ms)), float(np.percentile(ms, 90))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--algo", default="hydo-cm")
    ap.add_argument("--run", type=Path, default=None, help="a training run (default: a fresh agent)")
    ap.add_argument("--runs", type=int, default=300)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    torch.set_num_threads(2)

    from hydo_cli.config import TrainConfig, agent_config
    from hydo_cli.onnx_export import export_agent
    from hydo_cli.policies import load_agent
    from robot.onnx_policy import OnnxPolicy
    from sim.atomic import atomic_write_text
    from sim.env import BinEnv
    from sim.primitive import feasibility_mask

    if args.run is None:
        from models.algos import HybridAgent

        cfg = TrainConfig(algo=args.algo, objects="cube")
        agent = HybridAgent(agent_config(cfg))
    else:
        agent, cfg, _ = load_agent(args.run)
    folder = Path(tempfile.mkdtemp()) / "model"
    export_agent(agent, cfg, "bench/inference.py", folder, n_checks=16)
    policy = OnnxPolicy.load(folder)
    env = BinEnv(objects="train", goals="planar", n_obj=cfg.n_obj, n_bg=cfg.n_bg)
    obs, _ = env.reset(seed=0)
    pts, feats, nrm = obs["points"][None], obs["features"][None], obs["normals"][None]
    rng = np.random.default_rng(0)

    def torch_decision():
        with torch.no_grad():
            index, motion, _ = agent.act(
                torch.from_numpy(pts),
                torch.from_numpy(feats),
                mode="eval",
                normals=torch.from_numpy(nrm),
                feasible=feasibility_mask(pts, nrm),
            )
        return int(index[0])

    def ort_decision():
        return int(
            policy.decide(pts, feats, policy.noise(1, rng), nrm, feasibility_mask(pts, nrm))["index"][0]
        )

    per_graph = {"encoder": [], "actor": [], "critic": []}
    for _ in range(20):  # warm-up both
        torch_decision(), ort_decision()
    t_torch, t_ort = [], []
    for _ in range(args.runs):  # interleaved, so both see the same machine load
        t = time.perf_counter()
        torch_decision()
        t_torch.append((time.perf_counter() - t) * 1e3)
        t = time.perf_counter()
        ort_decision()
        t_ort.append((time.perf_counter() - t) * 1e3)
    noise = policy.noise(1, rng)
    for _ in range(args.runs):
        t0 = time.perf_counter()
        enc_inputs = {"points": pts, "features": feats} | ({"normals": nrm} if policy.needs_normals else {})
        pf = policy.encoder.run(None, enc_inputs)[0]
        t1 = time.perf_counter()
        motions = policy.actor.run(None, {"point_features": pf, "noise": noise})[0]
        t2 = time.perf_counter()
        policy.critic.run(None, {"point_features": pf, "motion": motions})
        t3 = time.perf_counter()
        per_graph["encoder"].append((t1 - t0) * 1e3)
        per_graph["actor"].append((t2 - t1) * 1e3)
        per_graph["critic"].append((t3 - t2) * 1e3)
    tm, tp = _stats(t_torch)
    om, op = _stats(t_ort)
    result = {
        "algo": cfg.algo,
        "n_obj": cfg.n_obj,
        "n_bg": cfg.n_bg,
        "denoise_steps": cfg.denoise_steps,
        "torch_ms_median": tm,
        "torch_ms_p90": tp,
        "ort_ms_median": om,
        "ort_ms_p90": op,
        "speedup": tm / om,
        **{f"ort_{k}_ms_median": _stats(v)[0] for k, v in per_graph.items()},
        "meta": {
            "command": " ".join(sys.argv),
            "torch": torch.__version__,
            "onnxruntime": __import__("onnxruntime").__version__,
            "threads": torch.get_num_threads(),
            "cpus": os.cpu_count(),
            "runs": args.runs,
            "time": time.strftime("%Y-%m-%d %H:%M:%S"),
        },
    }
    from rich.console import Console
    from rich.table import Table

    table = Table(title=f"one decision, {cfg.algo}, K={cfg.denoise_steps}, {cfg.n_obj}+{cfg.n_bg} points")
    for c in ("engine", "median ms", "p90 ms"):
        table.add_column(c)
    table.add_row("torch eager", f"{tm:.2f}", f"{tp:.2f}")
    table.add_row("onnxruntime", f"{om:.2f}", f"{op:.2f}")
    for k, v in per_graph.items():
        m, p = _stats(v)
        table.add_row(f"  ort {k}.onnx", f"{m:.2f}", f"{p:.2f}")
    table.caption = f"onnxruntime is {tm / om:.2f}x faster than torch eager"
    Console().print(table)
    if args.json:
        atomic_write_text(args.json, json.dumps(result, indent=2))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
