"""The training loop behind ``hydo train``: envs, agent, replay, logging, evaluation, checkpoints.

One process, ``n_envs`` envs in lock-step, one batched decision per step, then
``updates_per_step × n_envs`` gradient updates (CleanRL-style, top to bottom).
"""

from __future__ import annotations

import dataclasses
import json
import math
import resource
import signal
import time
from collections import deque
from pathlib import Path

import numpy as np
import torch

from hydo_cli.config import CHECKPOINT_FORMAT, TrainConfig, agent_config
from hydo_cli.envs import make_envs
from hydo_cli.policies import agent_policy
from hydo_cli.rollout import run_episodes, summarize
from models.algos import HybridAgent
from models.checkpoint import CheckpointError, load_checkpoint, save_checkpoint
from models.perf import configure_cpu
from models.replay import ReplayBuffer, Transition
from sim.contract import SUCCESS_THRESHOLD_M, pose_matrix

EVAL_SEED_OFFSET = 10_000  # evaluation episodes never share seeds with training episodes


class JsonlLog:
    """Append-only JSON lines, flushed per line: a crash loses at most the line being written.

    With a TensorBoard ``writer``, every numeric field is also logged as ``<tag>/<field>`` against
    ``env_steps``."""

    def __init__(self, path: Path, writer=None, tag: str = ""):
        self.f = open(path, "a", buffering=1)  # noqa: SIM115
        self.writer, self.tag = writer, tag

    def write(self, row: dict) -> None:
        self.f.write(json.dumps(row) + "\n")
        self.f.flush()
        if self.writer is not None:
            for k, v in row.items():
                if isinstance(v, int | float) and k != "env_steps":
                    self.writer.add_scalar(f"{self.tag}/{k}", v, global_step=row["env_steps"])


def tensorboard_writer(run_dir: Path):
    """A SummaryWriter on ``run_dir/tensorboard`` when the optional tensorboard package is installed."""
    try:
        from torch.utils.tensorboard import SummaryWriter
    except ImportError:
        return None
    return SummaryWriter(str(run_dir / "tensorboard"), flush_secs=30)


class Trainer:
    def __init__(self, cfg: TrainConfig, run_dir: Path, resume: bool = False):
        self.cpu = configure_cpu(cfg.threads)
        self.cfg, self.run_dir = cfg, Path(run_dir)
        self.envs = make_envs(
            cfg.objects,
            cfg.goals,
            cfg.clutter,
            "mesh",
            cfg.n_envs,
            cfg.n_obj,
            cfg.n_bg,
            task=cfg.task,
            task_start="random",
        )
        torch.manual_seed(cfg.seed)
        self.agent = HybridAgent(agent_config(cfg))
        self.buffer = ReplayBuffer(
            cfg.buffer_size, cfg.n_obj, cfg.n_bg, seed=cfg.seed, success_threshold=SUCCESS_THRESHOLD_M
        )
        self.rng = np.random.default_rng(cfg.seed)
        self.generator = torch.Generator().manual_seed(cfg.seed)
        self.env_steps = 0
        self.updates = 0
        self.episodes = 0
        self.wall_s = 0.0  # accumulated over resumes
        self.recent_success: deque[float] = deque(maxlen=100)
        self.recent_return: deque[float] = deque(maxlen=100)
        if resume:
            self.load()

    # --- checkpoints -----------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    def save(self) -> None:
        """Replay first, then the checkpoint that refers to it: a cut between the two loses nothing."""
        self.buffer.save(self.run_dir / "replay.npz")
        save_checkpoint(
            self.checkpoint_path,
            {
                "format": CHECKPOINT_FORMAT,
                "config": json.dumps(dataclasses.asdict(self.cfg)),
                "agent": self.agent.state_dict(),
                "counters": torch.tensor([self.env_steps, self.updates, self.episodes], dtype=torch.int64),
                "wall_s": torch.tensor(self.wall_s, dtype=torch.float64),
                "torch_rng": torch.get_rng_state(),
                "generator": self.generator.get_state(),
                "np_rng": json.dumps(self.rng.bit_generator.state),
            },
        )

    def load(self) -> None:
        ckpt = load_checkpoint(self.checkpoint_path)
        if int(ckpt.get("format", -1)) != CHECKPOINT_FORMAT:
            raise CheckpointError(
                f"{self.checkpoint_path}: checkpoint format {ckpt.get('format')} != {CHECKPOINT_FORMAT}"
            )
        self.agent.load_state_dict(ckpt["agent"])
        self.env_steps, self.updates, self.episodes = (int(v) for v in ckpt["counters"])
        self.wall_s = float(ckpt["wall_s"])
        torch.set_rng_state(ckpt["torch_rng"])
        self.generator.set_state(ckpt["generator"])
        self.rng.bit_generator.state = json.loads(ckpt["np_rng"])
        replay = self.run_dir / "replay.npz"
        if replay.exists():
            self.buffer = ReplayBuffer.load(replay)

    # --- the loop --------------------------------------------------------------------------------
    def evaluate(self) -> dict:
        policy = agent_policy(
            self.agent, "eval", torch.Generator().manual_seed(self.cfg.seed + EVAL_SEED_OFFSET)
        )
        results = run_episodes(
            self.envs, policy, self.cfg.eval_episodes, seed=self.cfg.seed + EVAL_SEED_OFFSET
        )
        return summarize(results)

    def run(self) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        cfg = self.cfg
        tb = tensorboard_writer(self.run_dir)
        metrics_log = JsonlLog(self.run_dir / "metrics.jsonl", tb, "train")
        eval_log = JsonlLog(self.run_dir / "eval.jsonl", tb, "eval")
        obs = [env.reset(seed=int(self.rng.integers(2**31)))[0] for env in self.envs]
        ep_return = np.zeros(len(self.envs))
        last_metrics: dict[str, float] = {}
        t_start = time.perf_counter() - self.wall_s
        updates_at_log, t_log = self.updates, time.perf_counter()
        update_debt = 0.0
        next_eval = (self.env_steps // cfg.eval_every + 1) * cfg.eval_every if cfg.eval_every else math.inf
        next_ckpt = (self.env_steps // cfg.checkpoint_every + 1) * cfg.checkpoint_every
        next_log = (self.env_steps // cfg.log_every + 1) * cfg.log_every
        interrupted = False

        def on_sigterm(signum, frame):  # treat SIGTERM like Ctrl-C: checkpoint, then stop
            raise KeyboardInterrupt

        old_handler = signal.signal(signal.SIGTERM, on_sigterm)
        progress = Progress(
            TextColumn(f"[bold]{cfg.algo}[/] {cfg.task or f'{cfg.goals}/{cfg.objects}'}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(),
            console=None,
            transient=False,
        )
        task = progress.add_task("train", total=cfg.steps, completed=self.env_steps, stats="")
        try:
            with progress:
                budget_s = cfg.max_minutes * 60 if cfg.max_minutes > 0 else math.inf
                while self.env_steps < cfg.steps and time.perf_counter() - t_start < budget_s:
                    # 1. act: random before learning starts, then the agent's exploration policy
                    if self.env_steps < cfg.learning_starts:
                        actions = [
                            (int(self.rng.integers(cfg.n_obj)), self.rng.uniform(-1, 1, 3).astype(np.float32))
                            for _ in self.envs
                        ]
                    else:
                        actions = agent_policy(self.agent, "explore", self.generator)(obs)
                    # 2. step every env; store real next observations (truncation still bootstraps)
                    rows: list[Transition] = []
                    for k, (env, action) in enumerate(zip(self.envs, actions, strict=True)):
                        next_obs, reward, terminated, truncated, info = env.step(action)
                        rows.append(
                            Transition(
                                points=obs[k]["points"],
                                features=obs[k]["features"],
                                index=action[0],
                                motion=action[1],
                                reward=reward,
                                next_points=next_obs["points"],
                                next_features=next_obs["features"],
                                terminated=terminated,
                                truncated=truncated,
                                goal_T=pose_matrix(info["goal_pose"][:3], info["goal_pose"][3:]),
                                achieved_T=pose_matrix(info["object_pose"][:3], info["object_pose"][3:]),
                                normals=obs[k]["normals"],
                                next_normals=next_obs["normals"],
                            )
                        )
                        ep_return[k] += reward
                        if terminated or truncated:
                            self.episodes += 1
                            self.recent_success.append(float(info["success"]))
                            self.recent_return.append(ep_return[k])
                            ep_return[k] = 0.0
                            next_obs, _ = env.reset(seed=int(self.rng.integers(2**31)))
                        obs[k] = next_obs
                    self.buffer.add(Transition(*(np.asarray(col) for col in zip(*rows, strict=True))))
                    self.env_steps += len(self.envs)
                    # 3. learn: updates_per_step gradient updates per env step, carried over fractions
                    if self.env_steps >= cfg.learning_starts and len(self.buffer) >= cfg.batch_size:
                        update_debt += cfg.updates_per_step * len(self.envs)
                        while update_debt >= 1.0:
                            sampled = self.buffer.sample(cfg.batch_size, cfg.relabel_future)
                            last_metrics = self.agent.update(sampled)
                            self.updates += 1
                            update_debt -= 1.0
                    # 4. log, evaluate, checkpoint
                    now = time.perf_counter()
                    if self.env_steps >= next_log:
                        ups = (self.updates - updates_at_log) / max(now - t_log, 1e-9)
                        updates_at_log, t_log = self.updates, now
                        row = {
                            "env_steps": self.env_steps,
                            "updates": self.updates,
                            "episodes": self.episodes,
                            "wall_s": now - t_start,
                            "updates_per_s": ups,
                            # peak resident memory of this process so far (Linux reports KiB)
                            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                            "replay_bytes_per_transition": self.buffer.bytes_per_transition,
                            "replay_size": len(self.buffer),
                            "success_recent": float(np.mean(self.recent_success))
                            if self.recent_success
                            else None,
                            "return_recent": float(np.mean(self.recent_return))
                            if self.recent_return
                            else None,
                            **{k: float(v) for k, v in last_metrics.items()},
                        }
                        metrics_log.write(row)
                        succ = row["success_recent"]
                        progress.update(
                            task,
                            stats=f"upd/s {ups:5.1f}  success {'-' if succ is None else f'{succ:.0%}'}"
                            f"  return {row['return_recent'] or 0:.3f}",
                        )
                        next_log += cfg.log_every
                    if self.env_steps >= next_eval:
                        self._eval_and_log(eval_log, t_start, progress)
                        next_eval += cfg.eval_every
                    if self.env_steps >= next_ckpt:
                        self.wall_s = time.perf_counter() - t_start
                        self.save()
                        next_ckpt += cfg.checkpoint_every
                    progress.update(task, completed=self.env_steps)
        except KeyboardInterrupt:
            interrupted = True
        finally:
            signal.signal(signal.SIGTERM, old_handler)
            if tb is not None:
                tb.flush()
        self.wall_s = time.perf_counter() - t_start
        self.save()
        if interrupted:
            progress.console.print(
                f"interrupted: checkpoint saved at {self.env_steps} env steps; resume with "
                f"`hydo train --resume {self.run_dir}`"
            )
            raise SystemExit(130)
        if not cfg.eval_every or self.env_steps % cfg.eval_every:
            self._eval_and_log(eval_log, t_start, progress)
        progress.console.print(
            f"done: {self.env_steps} env steps, {self.updates} updates in "
            f"{self.wall_s / 60:.1f} min; run in {self.run_dir}"
        )
        if tb is not None:
            tb.close()

    def _eval_and_log(self, eval_log: JsonlLog, t_start: float, progress) -> None:
        summary = self.evaluate()
        row = {
            "env_steps": self.env_steps,
            "updates": self.updates,
            "wall_s": time.perf_counter() - t_start,
            "success_rate": summary["success_rate"],
            "mean_return": summary["mean_return"],
            "episodes": summary["episodes"],
        }
        eval_log.write(row)
        progress.console.print(
            f"eval @ {self.env_steps} steps ({row['wall_s'] / 60:.1f} min): success {row['success_rate']:.0%} "
            f"over {row['episodes']} episodes, return {row['mean_return']:.3f}"
        )
