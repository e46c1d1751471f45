"""Can the encoder + critic architecture predict what a push does? A supervised probe on real data.

The learner's plateau is a ranking problem (``bench/lookahead.py``): among its own proposals the
critic does not tell the push that reaches the goal from the one that stops short. This probe takes
the TD noise out: it trains a fresh ``HybridAgent``'s encoder and first Q head (same architecture and
optimiser as training, from ``AgentConfig`` plus ``--set`` overrides) to regress the one-step
outcome ``d' = −r``, the mean goal-flow distance after the push, from ``(s, contact point, motion)``
of a run's replay buffer, and reports on held-out transitions:

* ``rmse_cm`` / ``train_rmse_cm``: fit on held-out / training transitions (equal: underfitting);
* ``near_rmse_cm``: on transitions that start within 7 cm of the goal (the pushes that decide
  success), next to ``no_change_rmse_cm``, the error of predicting that the distance stays the same;
* ``near_change_corr``: correlation of predicted and true change of distance near the goal (what
  ranking needs: 1 = perfect, 0 = none).

``--target displacement`` asks instead whether the *motion of the object* is easier to learn than
the distance: a head on the same per-point features predicts the rigid displacement ``D`` of the
object (a rotation vector and a translation about the observed centroid; trained on the squared
error of the moved object points ``D·p``), and the distance after the push follows without learning
from the stored flows: ``d' = mean_j ‖p_j + φ_j − D·p_j‖`` (the point ``p_j`` must reach
``p_j + φ_j``). The true ``D`` comes from the replay's poses (a run with hindsight poses):
``D = T_after · G⁻¹ · M`` with ``M = G · T_before⁻¹`` fitted (Kabsch) to the observed ``(p, p + φ)``.
The same metrics are reported on that implied ``d'``.

Usage::

    python bench/outcome.py --replay runs/train/hydo-cm-s1/replay.npz --steps 3000 --json runs/bench-outcome.json
    python bench/outcome.py --replay runs/train/hydo-cm-s1/replay.npz --set critic_hidden=128 --set encoder_knn=8
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402
import torch  # noqa: E402
from learner import parse_overrides  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

from models.algos import AgentConfig, HybridAgent  # noqa: E402
from models.perf import configure_cpu  # noqa: E402
from models.replay import ReplayBuffer  # noqa: E402
from sim.atomic import atomic_write_text  # noqa: E402

NEAR_GOAL_M = 0.07  # "near the goal": the observed mean flow before the push


def rotation_matrix(v: torch.Tensor) -> torch.Tensor:
    """Rotation vectors ``(M, 3)`` (radians) → matrices ``(M, 3, 3)`` (Rodrigues, smooth at 0)."""
    theta2 = (v * v).sum(-1, keepdim=True)[..., None]  # (M, 1, 1)
    k = torch.zeros(v.shape[0], 3, 3, dtype=v.dtype)
    k[:, 0, 1], k[:, 0, 2], k[:, 1, 2] = -v[:, 2], v[:, 1], -v[:, 0]
    k = k - k.transpose(1, 2)
    theta = theta2.clamp_min(1e-12).sqrt()
    a = torch.where(theta2 < 1e-8, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(theta2 < 1e-8, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / theta2.clamp_min(1e-12))
    return torch.eye(3, dtype=v.dtype) + a * k + b * (k @ k)


def true_moved_points(buf: ReplayBuffer, n: int) -> np.ndarray:
    """``D·p`` (n, N_obj, 3) float32: each transition's observed object points moved by the object's
    true displacement ``D = T_after · T_before⁻¹``, with ``T_before`` recovered from the flows."""
    p = buf.points[:n, : buf.n_obj].astype(np.float64)
    q = p + buf.features[:n, : buf.n_obj, 1:].astype(np.float64)  # the points in the goal pose
    pc, qc = p.mean(1, keepdims=True), q.mean(1, keepdims=True)
    u, _, vt = np.linalg.svd((p - pc).transpose(0, 2, 1) @ (q - qc))  # Kabsch: q ≈ R p + t
    d = np.sign(np.linalg.det(vt.transpose(0, 2, 1) @ u.transpose(0, 2, 1)))
    fix = np.ones((n, 3))
    fix[:, 2] = d
    r = vt.transpose(0, 2, 1) @ (fix[:, :, None] * u.transpose(0, 2, 1))  # (n, 3, 3)
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3], m[:, :3, 3] = r, (qc[:, 0] - (r @ pc[:, 0, :, None])[..., 0])
    g, after = (np.tile(np.eye(4), (n, 1, 1)) for _ in range(2))
    g[:, :3], after[:, :3] = buf.goal_T[:n], buf.achieved_T[:n]
    disp = after @ np.linalg.inv(g) @ m  # (n, 4, 4)
    return (p @ disp[:, :3, :3].transpose(0, 2, 1) + disp[:, None, :3, 3]).astype(np.float32)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--replay", type=Path, required=True, help="a run's replay.npz")
    ap.add_argument("--steps", type=int, default=3000, help="gradient steps")
    ap.add_argument("--batch-size", type=int, default=64)
    ap.add_argument("--test", type=int, default=4000, help="held-out transitions")
    ap.add_argument("--threads", type=int, default=1, help="torch.set_num_threads")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE", help="AgentConfig override")
    ap.add_argument("--json", type=Path, help="write results to this JSON file")
    ap.add_argument(
        "--target",
        choices=("distance", "displacement"),
        default="distance",
        help="regress d' directly, or the object's rigid displacement (d' then follows from the flows)",
    )
    args = ap.parse_args(argv)

    configure_cpu(args.threads)
    buf = ReplayBuffer.load(args.replay)
    n = len(buf)
    cfg = AgentConfig(
        algo="hydo-cm", n_obj=buf.n_obj, n_bg=buf.n_bg, seed=args.seed, **parse_overrides(args.set)
    )
    agent = HybridAgent(cfg)
    encoder, critic = agent.encoder, agent.critic
    optimizer = torch.optim.Adam([*encoder.parameters(), *critic.parameters()], lr=cfg.lr_critic)

    target = torch.from_numpy(-buf.reward[:n].astype(np.float32))  # (n,) d' in metres
    flow = buf.features[:n, : buf.n_obj, 1:].astype(np.float32)
    d_before = torch.from_numpy(np.linalg.norm(flow, axis=-1).mean(-1))  # (n,) observed distance before
    perm = torch.randperm(n, generator=torch.Generator().manual_seed(args.seed))
    test, train = perm[: args.test], perm[args.test :]

    obj = slice(0, buf.n_obj)
    if args.target == "displacement":
        if not buf.has_poses[:n].all():
            raise SystemExit(
                "--target displacement needs a replay stored with poses (hydo train of this version)"
            )
        moved = torch.from_numpy(true_moved_points(buf, n))  # (n, N_obj, 3): D·p, metres
        dim = cfg.feature_dim + 3
        disp_head = torch.nn.Sequential(
            torch.nn.Linear(dim, cfg.critic_hidden), torch.nn.ReLU(),
            torch.nn.Linear(cfg.critic_hidden, cfg.critic_hidden), torch.nn.ReLU(),
            torch.nn.Linear(cfg.critic_hidden, 6),
        )  # fmt: skip
        optimizer = torch.optim.Adam([*encoder.parameters(), *disp_head.parameters()], lr=cfg.lr_critic)

    def moved_points(idx: torch.Tensor) -> torch.Tensor:
        """Predicted object points after the push ``(M, N_obj, 3)`` metres (displacement target)."""
        points = torch.from_numpy(buf.points[idx.numpy()].astype(np.float32))
        features = torch.from_numpy(buf.features[idx.numpy()].astype(np.float32))
        normals = torch.from_numpy(buf.normals[idx.numpy()].astype(np.float32))
        f = encoder(points, features, normals)  # (M, N_obj, D)
        index = torch.from_numpy(buf.index[idx.numpy()].astype(np.int64))
        motion = torch.from_numpy(buf.motion[idx.numpy()])
        out = disp_head(torch.cat([f[torch.arange(len(idx)), index], motion], dim=-1))  # (M, 6)
        rot = rotation_matrix(out[:, :3])  # (M, 3, 3)
        p = points[:, obj]
        centre = p.mean(dim=1, keepdim=True)
        return (p - centre) @ rot.transpose(1, 2) + centre + 0.1 * out[:, None, 3:]

    def predict(idx: torch.Tensor) -> torch.Tensor:
        """Predicted d' (metres) for transitions ``idx (M,)``."""
        points = torch.from_numpy(buf.points[idx.numpy()].astype(np.float32))
        features = torch.from_numpy(buf.features[idx.numpy()].astype(np.float32))
        if args.target == "displacement":
            goal_points = points[:, obj] + features[:, obj, 1:]
            return (goal_points - moved_points(idx)).norm(dim=-1).mean(-1)  # (M,)
        normals = torch.from_numpy(buf.normals[idx.numpy()].astype(np.float32))
        f = encoder(points, features, normals)  # (M, N_obj, D)
        index = torch.from_numpy(buf.index[idx.numpy()].astype(np.int64))
        motion = torch.from_numpy(buf.motion[idx.numpy()])
        return critic.q1(f[torch.arange(len(idx)), index], motion)  # (M,)

    def evaluate(idx: torch.Tensor) -> dict:
        with torch.no_grad():
            pred = torch.cat([predict(idx[i : i + 500]) for i in range(0, len(idx), 500)])
        err, y, d0 = pred - target[idx], target[idx], d_before[idx]
        near = d0 < NEAR_GOAL_M
        corr = torch.corrcoef(torch.stack([pred[near] - d0[near], y[near] - d0[near]]))[0, 1]
        return {
            "rmse_cm": float(err.pow(2).mean().sqrt() * 100),
            "near_rmse_cm": float(err[near].pow(2).mean().sqrt() * 100),
            "no_change_rmse_cm": float((d0[near] - y[near]).pow(2).mean().sqrt() * 100),
            "near_change_corr": float(corr),
            "near_n": int(near.sum()),
        }

    gen = torch.Generator().manual_seed(args.seed + 1)
    curve, t0 = [], time.perf_counter()
    for step in range(1, args.steps + 1):
        idx = train[torch.randint(len(train), (args.batch_size,), generator=gen)]
        if args.target == "displacement":  # squared error of the moved points, in 10 cm units
            loss = ((moved_points(idx) - moved[idx]) * 10.0).pow(2).sum(-1).mean()
        else:
            loss = (predict(idx) - target[idx]).pow(2).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        if step % 1000 == 0 or step == args.steps:
            row = {"step": step, "wall_s": round(time.perf_counter() - t0, 1), **evaluate(test)}
            row["train_rmse_cm"] = evaluate(train[: args.test])["rmse_cm"]
            curve.append(row)

    table = Table(
        title=f"one-step outcome fit, {args.target} target ({args.replay}, {n} transitions, "
        f"overrides {args.set or 'none'})"
    )
    for col in (
        "step",
        "rmse cm",
        "train rmse cm",
        "near-goal rmse cm",
        "no-change cm",
        "near corr",
        "wall s",
    ):
        table.add_column(col, justify="right")
    for r in curve:
        table.add_row(
            str(r["step"]),
            f"{r['rmse_cm']:.2f}",
            f"{r['train_rmse_cm']:.2f}",
            f"{r['near_rmse_cm']:.2f}",
            f"{r['no_change_rmse_cm']:.2f}",
            f"{r['near_change_corr']:.3f}",
            f"{r['wall_s']:.0f}",
        )
    Console().print(table)
    if args.json:
        meta = {
            "replay": str(args.replay),
            "transitions": n,
            "overrides": args.set,
            "target": args.target,
            "agent_config": cfg.to_dict(),
            "threads": args.threads,
            "torch": torch.__version__,
            "machine": platform.processor() or platform.machine(),
            "command": " ".join(
                ["python", "bench/outcome.py", *(argv if argv is not None else sys.argv[1:])]
            ),
        }
        atomic_write_text(args.json, json.dumps({"curve": curve, "final": curve[-1], "meta": meta}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
