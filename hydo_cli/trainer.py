"""The training loop behind ``hydo train``: envs, agent, replay, logging, evaluation, checkpoints.

``workers`` processes (default 2, one per core) train one agent data-parallel
(``models.distributed``): each steps ``n_envs / workers`` envs in lock-step into its own replay shard,
makes one batched decision per step, then takes ``updates_per_step × n_envs`` gradient updates on
``batch_size / workers`` transitions of its shard, averaging gradients with the others before every
optimiser step. The update-to-data ratio is a setting, the same for any number of workers: every
worker does the same number of updates per env step, by construction, not by timing. Worker 0 logs,
writes ``checkpoint.pt``; every worker plays its share of each evaluation's episodes, and worker 0
logs their results; worker ``r`` > 0 saves ``replay-r.npz`` and ``worker-r.pt``
(its RNG states) beside it. ``workers=1`` is the serial loop (CleanRL-style, top to bottom).
"""

from __future__ import annotations

import dataclasses
import json
import math
import multiprocessing
import os
import resource
import signal
import sys
import threading
import time
import traceback
from collections import deque
from pathlib import Path

import numpy as np
import torch

from hydo_cli.config import CHECKPOINT_FORMAT, TrainConfig, agent_config
from hydo_cli.envs import make_envs
from hydo_cli.errors import HydoError
from hydo_cli.policies import agent_policy
from hydo_cli.rollout import run_episodes
from models.algos import AgentConfig, HybridAgent
from models.checkpoint import (
    CheckpointError,
    apply_replay_segment,
    load_checkpoint,
    load_replay,
    save_checkpoint,
)
from models.distributed import GroupSpec, WorkerGroup, make_group
from models.perf import configure_cpu, resolve_precision, update_autocast
from models.replay import ReplayBuffer, Transition
from sim.atomic import atomic_write_text
from sim.contract import SUCCESS_THRESHOLD_M, pose_matrix
from sim.symmetry import symmetries

EVAL_SEED_OFFSET = 10_000  # evaluation episodes never share seeds with training episodes
LOGS = ("metrics.jsonl", "eval.jsonl")
STOP_BUDGET, STOP_SIGNAL = 1, 2  # why the workers stop (the largest reason any worker gives wins)


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


def read_run_checkpoint(path: Path) -> dict:
    """A run's ``checkpoint.pt`` payload, or one clear error (unreadable, another format, no agent)."""
    ckpt = load_checkpoint(path)
    if int(ckpt.get("format", -1)) != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: checkpoint format {ckpt.get('format')} != {CHECKPOINT_FORMAT}")
    if not isinstance(ckpt.get("agent"), dict) or not isinstance(ckpt["agent"].get("config"), dict):
        raise CheckpointError(path, "holds no agent state")
    return ckpt


def truncate_logs(run_dir: Path, env_steps: int) -> None:
    """Drop the log rows a cut run wrote after its last checkpoint (and unreadable half lines), so a
    resumed run's history never repeats steps."""
    for name in LOGS:
        path = run_dir / name
        if not path.exists():
            continue
        kept = []
        for line in path.read_text().splitlines():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                continue  # the line being written when the run was killed
            if isinstance(row, dict) and row.get("env_steps", math.inf) <= env_steps:
                kept.append(line)
        atomic_write_text(path, "".join(f"{line}\n" for line in kept))


class Trainer:
    """One worker of a training run (``rank`` 0 is the one ``hydo train`` runs and spawns the others).

    ``resume``: continue from ``run_dir/checkpoint.pt`` (a folder without one, left by a run cut
    before its first checkpoint, restarts from step 0 with its logs emptied). ``fresh_replay``: on
    resume, start from empty replay shards when they are missing instead of refusing.
    """

    def __init__(
        self,
        cfg: TrainConfig,
        run_dir: Path,
        resume: bool = False,
        rank: int = 0,
        fresh_replay: bool = False,
    ):
        self.cpu = configure_cpu(cfg.threads)
        self.precision = self.cpu["precision"] = resolve_precision(cfg.precision)
        self.run_dir = Path(run_dir)
        self.rank, self.world = rank, cfg.workers
        ckpt = read_run_checkpoint(self.checkpoint_path) if resume and self.checkpoint_path.exists() else None
        self.resumed = ckpt is not None
        # The checkpoint's own agent config wins: a run made under older defaults resumes with them.
        agent_cfg = AgentConfig.from_dict(ckpt["agent"]["config"]) if ckpt else agent_config(cfg)
        self.cfg = cfg = dataclasses.replace(cfg, agent=dataclasses.asdict(agent_cfg))  # the full record
        self.envs = make_envs(
            cfg.objects,
            cfg.goals,
            cfg.clutter,
            "mesh",
            cfg.n_envs // self.world,
            cfg.n_obj,
            cfg.n_bg,
            task=cfg.task,
            task_start="random",
            flip_share=cfg.flip_share,
            contacts=cfg.contacts,
        )
        # Worker 0 keeps the serial loop's seeding; the others draw their own episodes and noise.
        seed = cfg.seed if rank == 0 else cfg.seed + 1_000_003 * rank
        torch.manual_seed(seed)
        self.agent = HybridAgent(agent_cfg)  # identical initial weights on every worker
        if rank:
            self.agent.generator.manual_seed(seed + 1)
        self.buffer = ReplayBuffer(
            cfg.buffer_size // self.world,
            cfg.n_obj,
            cfg.n_bg,
            seed=seed,
            success_threshold=SUCCESS_THRESHOLD_M,
        )
        # Hindsight goals up to the object's symmetry: each transition records its object's row in
        # the run's object set (the same order on every worker and resume), the replay its symmetries.
        assets = self.envs[0].assets
        self.object_ids = {a.name: i for i, a in enumerate(assets)}
        self.symmetries = tuple(symmetries(a) for a in assets) if cfg.relabel_future else ()
        self.buffer.symmetries = self.symmetries
        self.rng = np.random.default_rng(seed)
        self.generator = torch.Generator().manual_seed(seed)
        self.env_steps = 0
        self.updates = 0
        self.episodes = 0
        self.wall_s = 0.0  # accumulated over resumes
        self.recent_success: deque[float] = deque(maxlen=100)
        self.recent_return: deque[float] = deque(maxlen=100)
        self.stop_reason = 0
        self.group: WorkerGroup | None = None
        # every worker's seconds waiting at the group's barriers so far, as of the last exchange
        self.sync_wait_s = np.zeros(self.world)
        # Replay on disk: a snapshot (replay.npz) plus one segment per later checkpoint (save()).
        self.replay_seq = 0  # saves of this worker's shard so far (snapshots and segments)
        self.replay_logged = 0  # transitions written as segments since the snapshot
        self.replay_snapshot_due = True  # the next save writes a whole snapshot
        self.replay_snapshot_seq = 0  # the save that wrote the snapshot on disk
        if ckpt is not None:
            self.load(ckpt, fresh_replay)
        elif resume and rank == 0:  # a run cut before its first checkpoint: from step 0, clean logs
            truncate_logs(self.run_dir, -1)

    # --- checkpoints -----------------------------------------------------------------------------
    @property
    def checkpoint_path(self) -> Path:
        return self.run_dir / "checkpoint.pt"

    def shard_paths(self, rank: int) -> tuple[Path, Path]:
        """Worker ``rank``'s replay snapshot and (rank > 0) its own state file."""
        return shard_files(self.run_dir, rank)

    def segment_path(self, rank: int, seq: int) -> Path:
        """Worker ``rank``'s replay segment of save ``seq``."""
        return segment_file(self.run_dir, rank, seq)

    def _save_replay(self) -> dict:
        """This worker's shard: a whole snapshot when due (the first save, after a resume that could
        not continue the segments, or once the segments since the snapshot hold a capacity's worth of
        transitions), else a segment of what the last interval added. A full shard is ~0.9 GB and
        took 5–11 s to write at every checkpoint; a segment is ~1 % of that. Returns the state the
        checkpoint records."""
        snapshot, _ = self.shard_paths(self.rank)
        self.replay_seq += 1
        if self.replay_snapshot_due or self.replay_logged + self.buffer.unsaved > self.buffer.capacity:
            self.buffer.save(snapshot, seq=self.replay_seq)
            self.replay_logged, self.replay_snapshot_due = 0, False
            self.replay_snapshot_seq = self.replay_seq
        else:
            self.replay_logged += self.buffer.save_segment(self.segment_path(self.rank, self.replay_seq))
        return {"replay_seq": self.replay_seq, "replay_logged": self.replay_logged}

    def _drop_stale_segments(self) -> None:
        """Once this worker's state records the new save: segments the snapshot already holds, and any
        a cut run left beyond it, are removed."""
        keep = range(self.replay_snapshot_seq + 1, self.replay_seq + 1)
        stem = self.shard_paths(self.rank)[0].stem
        for path in self.run_dir.glob(f"{stem}.s*.npz"):
            seq = path.name[len(stem) + 2 : -len(".npz")]
            if seq.isdigit() and int(seq) not in keep:
                path.unlink(missing_ok=True)

    def _rng_state(self) -> dict:
        return {
            "torch_rng": torch.get_rng_state(),
            "generator": self.generator.get_state(),
            "np_rng": json.dumps(self.rng.bit_generator.state),
        }

    def save(self) -> None:
        """Every worker writes its replay shard (and worker r > 0 its RNG states); then worker 0 writes
        the checkpoint that refers to them. A cut in between loses nothing: the shards are at most a
        checkpoint interval newer than the checkpoint."""
        _, state = self.shard_paths(self.rank)
        replay_state = self._save_replay()
        if self.rank:
            save_checkpoint(
                state,
                {
                    "format": CHECKPOINT_FORMAT,
                    "env_steps": self.env_steps,
                    "agent_generator": self.agent.generator.get_state(),
                    **replay_state,
                    **self._rng_state(),
                },
            )
            self._drop_stale_segments()
        if self.group is not None:
            self.group.barrier()
        if self.rank == 0:
            save_checkpoint(
                self.checkpoint_path,
                {
                    "format": CHECKPOINT_FORMAT,
                    "config": json.dumps(dataclasses.asdict(self.cfg)),
                    "agent": self.agent.state_dict(),
                    "counters": torch.tensor(
                        [self.env_steps, self.updates, self.episodes], dtype=torch.int64
                    ),
                    "wall_s": torch.tensor(self.wall_s, dtype=torch.float64),
                    "workers": self.world,
                    # every shard's (pos, full): they grow in lock-step
                    "replay_at": (self.buffer.pos, self.buffer.full),
                    **replay_state,
                    **self._rng_state(),
                },
            )
            self._drop_stale_segments()

    def load(self, ckpt: dict, fresh_replay: bool = False) -> None:
        saved_workers = int(ckpt.get("workers", 1))
        if saved_workers != self.world:
            raise HydoError(
                f"{self.checkpoint_path} was trained with {saved_workers} worker(s) (replay shards); "
                f"resume it with the same --workers, not {self.world}"
            )
        self.agent.load_state_dict(ckpt["agent"])
        self.env_steps, self.updates, self.episodes = (int(v) for v in ckpt["counters"])
        self.wall_s = float(ckpt["wall_s"])
        state = ckpt
        replay, state_path = self.shard_paths(self.rank)
        if self.rank:
            state = read_worker_state(state_path)
            self.agent.generator.set_state(state["agent_generator"])
        torch.set_rng_state(state["torch_rng"])
        self.generator.set_state(state["generator"])
        self.rng.bit_generator.state = json.loads(state["np_rng"])
        if replay.exists():
            self.buffer, log = load_shard(self.run_dir, self.rank, state, self.cfg.n_obj, self.cfg.n_bg)
            self.buffer.symmetries = self.symmetries
            self.replay_seq, self.replay_snapshot_seq = log["replay_seq"], log["replay_snapshot_seq"]
            self.replay_logged, self.replay_snapshot_due = log["replay_logged"], not log["continued"]
            # the shard was saved just before the checkpoint: a cut in between leaves it ahead
            at = tuple(ckpt.get("replay_at", (self.buffer.pos, self.buffer.full)))
            if (self.buffer.pos, self.buffer.full) != (at[0], bool(at[1])):
                self.replay_snapshot_due = True  # what is on disk is ahead of the checkpoint
            self.buffer.rewind(*at)
        elif not fresh_replay:
            raise HydoError(
                f"{replay} is missing: resuming would train on an empty replay buffer. "
                "Restore it, or pass --fresh-replay to continue with an empty one"
            )
        if self.rank == 0:
            truncate_logs(self.run_dir, self.env_steps)

    def check_resumable(self, fresh_replay: bool) -> None:
        """Worker 0, before spawning the others: every worker's files are there (so no worker fails
        after the others started waiting for it)."""
        for r in range(1, self.world):
            replay, state = self.shard_paths(r)
            seq = read_worker_state(state).get("replay_seq")
            if not replay.exists() and not fresh_replay:
                raise HydoError(
                    f"{replay} is missing: resuming would train on an empty replay shard. "
                    "Restore it, or pass --fresh-replay to continue with an empty one"
                )
            snap = _snapshot_seq(replay) if replay.exists() and seq is not None else None
            for k in range(snap + 1, int(seq) + 1) if snap is not None else ():
                if not self.segment_path(r, k).exists():
                    raise HydoError(
                        f"{self.segment_path(r, k)} is missing: worker {r}'s replay shard cannot be rebuilt"
                    )

    # --- the loop --------------------------------------------------------------------------------
    def evaluate(self) -> dict:
        """Every worker: play this worker's share of the ``eval_episodes`` (episodes ``rank``,
        ``rank + workers``, …: the same seeded episodes whatever the number of workers) on its envs,
        then pool every worker's results. Returns ``episodes``, ``success_rate``, ``mean_return``.

        Shared, so that an evaluation takes ``1 / workers`` of the time and no worker sits at the next
        sync while another evaluates. The replicas hold the same weights, so the policy is the same."""
        policy = agent_policy(
            self.agent, "eval", torch.Generator().manual_seed(self.cfg.seed + EVAL_SEED_OFFSET + self.rank)
        )
        for env in self.envs:  # evaluate on goals as drawn, whatever mix training uses
            env.flip_share = None
        try:
            results = run_episodes(
                self.envs,
                policy,
                self.cfg.eval_episodes,
                seed=self.cfg.seed + EVAL_SEED_OFFSET,
                shard=(self.rank, self.world),
            )
        finally:
            for env in self.envs:
                env.flip_share = self.cfg.flip_share
        row = np.array(
            [len(results), sum(r.success for r in results), sum(r.episode_return for r in results)], float
        )
        n, successes, returns = (self.group.gather(row) if self.group is not None else row[None]).sum(0)
        return {
            "episodes": int(n),
            "success_rate": successes / n if n else 0.0,
            "mean_return": returns / n if n else 0.0,
        }

    def run(self, fresh_replay: bool = False) -> None:
        """Worker 0: start the other workers, train, and report (``hydo train`` calls this)."""
        if self.world == 1:
            self._train()
            return
        if self.resumed:
            self.check_resumable(fresh_replay)
        spec = make_group(self.world, self.agent.num_parameters() + 2, 3 + 2 * len(self.envs))
        ctx = multiprocessing.get_context("spawn")
        cfg = dataclasses.asdict(self.cfg)
        workers = [
            ctx.Process(
                target=_worker_main,
                args=(cfg, str(self.run_dir), self.resumed, rank, spec, fresh_replay),
                daemon=True,
                name=f"hydo-worker-{rank}",
            )
            for rank in range(1, self.world)
        ]
        for w in workers:
            w.start()
        done = threading.Event()
        threading.Thread(target=_watch_workers, args=(workers, done), daemon=True).start()
        self.group = WorkerGroup(0, spec)
        try:
            self._train()
        except BaseException:
            self.group.abort()  # the other workers stop at their next collective
            raise
        finally:
            done.set()
            for w in workers:
                w.join(timeout=60)

    def _exchange(self, stop: int, finished: list[tuple[float, float]]) -> int:
        """Once per step, every worker: agree on stopping (the largest reason), pool the episodes
        that ended (``(success, return)`` each) into the recent-success window and share the seconds
        each worker has waited at the barriers (``sync_wait_s``). Returns the reason."""
        if self.group is None:
            rows = [(stop, finished)]
        else:
            k = len(self.envs)  # at most one episode per env per step
            row = np.zeros(3 + 2 * k)
            row[0], row[1], row[2] = stop, len(finished), self.group.wait_s
            for j, (succ, ret) in enumerate(finished):
                row[3 + j], row[3 + k + j] = succ, ret
            gathered = self.group.gather(row)  # (world, 3 + 2k)
            self.sync_wait_s = gathered[:, 2].copy()
            rows = [(int(r[0]), [(r[3 + j], r[3 + k + j]) for j in range(int(r[1]))]) for r in gathered]
        for _, eps in rows:
            for succ, ret in eps:
                self.episodes += 1
                self.recent_success.append(float(succ))
                self.recent_return.append(float(ret))
        return max(r for r, _ in rows)

    def _train(self) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        cfg, lead = self.cfg, self.rank == 0
        if self.group is not None:
            self.agent.sync_gradients = self.group.average_gradients
        batch_size = cfg.batch_size // self.world
        tb = tensorboard_writer(self.run_dir) if lead else None
        metrics_log = JsonlLog(self.run_dir / "metrics.jsonl", tb, "train") if lead else None
        eval_log = JsonlLog(self.run_dir / "eval.jsonl", tb, "eval") if lead else None

        def start_episodes() -> list[dict]:
            """A new episode in every env: its first observations."""
            return [env.reset(seed=int(self.rng.integers(2**31)))[0] for env in self.envs]

        obs = start_episodes()
        ep_return = np.zeros(len(self.envs))
        finished: list[tuple[float, float]] = []
        last_metrics: dict[str, float] = {}
        t_start = time.perf_counter() - self.wall_s
        updates_at_log, t_log = self.updates, time.perf_counter()
        wait_at_log = self.sync_wait_s.copy()
        update_debt = 0.0
        next_eval = (self.env_steps // cfg.eval_every + 1) * cfg.eval_every if cfg.eval_every else math.inf
        next_ckpt = (self.env_steps // cfg.checkpoint_every + 1) * cfg.checkpoint_every
        next_log = (self.env_steps // cfg.log_every + 1) * cfg.log_every
        budget_s = cfg.max_minutes * 60 if cfg.max_minutes > 0 else math.inf
        signalled = False

        def on_signal(signum, frame):
            # Ctrl-C / SIGTERM: finish the step, agree with the other workers, checkpoint, stop. A
            # second one stops at once (the last checkpoint stays valid: writes are atomic).
            nonlocal signalled
            if signalled:
                raise KeyboardInterrupt
            signalled = True

        old_handlers = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
        progress = Progress(
            TextColumn(f"[bold]{cfg.algo}[/] {cfg.task or f'{cfg.goals}/{cfg.objects}'}"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("{task.fields[stats]}"),
            TimeElapsedColumn(),
            console=None,
            transient=False,
            disable=not lead,
        )
        task = progress.add_task("train", total=cfg.steps, completed=self.env_steps, stats="")
        try:
            with progress:
                while self.env_steps < cfg.steps:
                    over_budget = lead and time.perf_counter() - t_start >= budget_s
                    local_stop = STOP_SIGNAL if signalled else STOP_BUDGET if over_budget else 0
                    self.stop_reason = self._exchange(local_stop, finished)
                    finished = []
                    if self.stop_reason:
                        break
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
                        # the pose each observation's goal flow points to (the nearest that looks
                        # like the goal: it can change with the object's pose) for hindsight goals
                        flow_goal_T = env.T_goal_eff.copy()
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
                                goal_T=flow_goal_T,
                                achieved_T=pose_matrix(info["object_pose"][:3], info["object_pose"][3:]),
                                normals=obs[k]["normals"],
                                next_normals=next_obs["normals"],
                                next_goal_T=env.T_goal_eff.copy(),
                                object_id=self.object_ids[env.scene.asset.name],
                            )
                        )
                        ep_return[k] += reward
                        if terminated or truncated:
                            finished.append((float(info["success"]), float(ep_return[k])))
                            ep_return[k] = 0.0
                            next_obs, _ = env.reset(seed=int(self.rng.integers(2**31)))
                        obs[k] = next_obs
                    self.buffer.add(Transition(*(np.asarray(col) for col in zip(*rows, strict=True))))
                    self.env_steps += cfg.n_envs  # all workers stepped their share
                    # 3. learn: updates_per_step gradient updates per env step, carried over fractions
                    if self.env_steps >= cfg.learning_starts and len(self.buffer) >= batch_size:
                        update_debt += cfg.updates_per_step * cfg.n_envs
                        while update_debt >= 1.0:
                            sampled = self.buffer.sample(
                                batch_size, cfg.relabel_future, cfg.n_step, self.agent.config.gamma
                            )
                            with update_autocast(self.precision):
                                last_metrics = self.agent.update(sampled)
                            self.updates += 1
                            update_debt -= 1.0
                    # 4. log (worker 0), evaluate and checkpoint (every worker)
                    now = time.perf_counter()
                    if self.env_steps >= next_log:
                        dt_log = max(now - t_log, 1e-9)
                        ups = (self.updates - updates_at_log) / dt_log
                        # the share of the interval the workers sat at the barriers (their mean)
                        waited = float(np.mean(self.sync_wait_s - wait_at_log)) / dt_log
                        updates_at_log, t_log, wait_at_log = self.updates, now, self.sync_wait_s.copy()
                        if lead:
                            row = self._metrics_row(now - t_start, ups, waited, last_metrics)
                            metrics_log.write(row)
                            left = budget_s - (now - t_start)
                            succ = row["success_recent"]
                            progress.update(
                                task,
                                stats=f"upd/s {ups:5.1f}  success {'-' if succ is None else f'{succ:.0%}'}"
                                f"  return {row['return_recent'] or 0:.3f}"
                                + (f"  {left / 60:.0f} min left" if math.isfinite(left) else ""),
                            )
                        next_log += cfg.log_every
                    if self.env_steps >= next_eval:
                        self._eval_and_log(eval_log, t_start, progress)
                        # it played its own episodes on these envs: the interrupted ones end here
                        obs = start_episodes()
                        self.buffer.end_episodes()
                        ep_return[:] = 0.0
                        next_eval += cfg.eval_every
                    if self.env_steps >= next_ckpt:
                        self.wall_s = time.perf_counter() - t_start
                        self.save()
                        next_ckpt += cfg.checkpoint_every
                    progress.update(task, completed=self.env_steps)
        finally:
            for s, h in old_handlers.items():
                signal.signal(s, h)
            if tb is not None:
                tb.flush()
        self.wall_s = time.perf_counter() - t_start
        self.save()
        # a last evaluation of the final weights unless the loop just made one (every worker: the
        # stop reason is agreed, so all of them take the same branch)
        if self.stop_reason != STOP_SIGNAL and (not cfg.eval_every or self.env_steps % cfg.eval_every):
            self._eval_and_log(eval_log, t_start, progress)
        if not lead:
            return
        if self.stop_reason == STOP_SIGNAL:
            progress.console.print(
                f"interrupted: checkpoint saved at {self.env_steps} env steps; resume with "
                f"`hydo train --resume {self.run_dir}`"
            )
            raise SystemExit(130)
        progress.console.print(
            f"done: {self.env_steps} env steps, {self.updates} updates in "
            f"{self.wall_s / 60:.1f} min; run in {self.run_dir}"
        )
        if tb is not None:
            tb.close()

    def _metrics_row(self, wall_s: float, ups: float, waited: float, last_metrics: dict[str, float]) -> dict:
        return {
            "env_steps": self.env_steps,
            "updates": self.updates,
            "episodes": self.episodes,
            "wall_s": wall_s,
            "updates_per_s": ups,
            "workers": self.world,
            # the lock-step's idle time: the mean share of the last log interval that the workers
            # spent waiting at gradient syncs and exchanges (None with one worker: nothing to wait for)
            "sync_wait_share": waited if self.world > 1 else None,
            "precision": self.precision,
            # peak resident memory of this process so far (Linux reports KiB)
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
            "replay_bytes_per_transition": self.buffer.bytes_per_transition,
            "replay_size": len(self.buffer) * self.world,
            "success_recent": float(np.mean(self.recent_success)) if self.recent_success else None,
            "return_recent": float(np.mean(self.recent_return)) if self.recent_return else None,
            **{k: float(v) for k, v in last_metrics.items()},
        }

    def _eval_and_log(self, eval_log: JsonlLog | None, t_start: float, progress) -> None:
        """Every worker evaluates (``evaluate``); worker 0 writes the row and prints it."""
        t_eval = time.perf_counter()
        summary = self.evaluate()
        if eval_log is None:
            return
        now = time.perf_counter()
        row = {
            "env_steps": self.env_steps,
            "updates": self.updates,
            "wall_s": now - t_start,
            "success_rate": summary["success_rate"],
            "mean_return": summary["mean_return"],
            "episodes": summary["episodes"],
            "eval_s": now - t_eval,  # the evaluation's own wall time (training stood still for it)
        }
        eval_log.write(row)
        progress.console.print(
            f"eval @ {self.env_steps} steps ({row['wall_s'] / 60:.1f} min): success {row['success_rate']:.0%} "
            f"over {row['episodes']} episodes, return {row['mean_return']:.3f}"
        )


def shard_files(run_dir: Path, rank: int) -> tuple[Path, Path]:
    """Worker ``rank``'s replay snapshot and the file that records its state (``checkpoint.pt`` for
    worker 0, ``worker-r.pt`` for the others)."""
    if rank == 0:
        return run_dir / "replay.npz", run_dir / "checkpoint.pt"
    return run_dir / f"replay-{rank}.npz", run_dir / f"worker-{rank}.pt"


def segment_file(run_dir: Path, rank: int, seq: int) -> Path:
    """Worker ``rank``'s replay segment of save ``seq`` (``replay.s00012.npz``, ``replay-1.s00012.npz``)."""
    return shard_files(run_dir, rank)[0].with_suffix(f".s{seq:05d}.npz")


def load_shard(run_dir: Path, rank: int, state: dict, n_obj: int, n_bg: int) -> tuple[ReplayBuffer, dict]:
    """Worker ``rank``'s replay shard as its ``state`` (checkpoint or worker state) last saved it: the
    snapshot, then, in order, the segments saved after it. Returns the buffer and where the segment log
    stands (``replay_seq``, ``replay_snapshot_seq``, ``replay_logged``, ``continued``). A run from
    before segments (no ``replay_seq``), or a snapshot newer than the state (a cut between the two),
    takes no segment: ``continued`` is False and the next save must write a whole snapshot."""
    buffer = load_replay(shard_files(run_dir, rank)[0], n_obj, n_bg)
    seq, snap = state.get("replay_seq"), buffer.snapshot_seq
    if seq is None or snap is None or snap > int(seq):
        top = max(int(seq or 0), snap or 0)
        return buffer, {"replay_seq": top, "replay_snapshot_seq": top, "replay_logged": 0, "continued": False}
    for k in range(snap + 1, int(seq) + 1):
        apply_replay_segment(buffer, segment_file(run_dir, rank, k))
    log = {"replay_seq": int(seq), "replay_snapshot_seq": snap, "continued": True}
    return buffer, {**log, "replay_logged": int(state.get("replay_logged", 0))}


def _snapshot_seq(path: Path) -> int | None:
    """The ``seq`` a replay snapshot records, read without loading its arrays (None: none, or unreadable:
    the worker's own load then names the problem)."""
    try:
        with np.load(path, allow_pickle=False) as z:
            return int(z["seq"]) if "seq" in z.files else None
    except Exception:  # noqa: BLE001 - any damage is reported by load_replay in the worker
        return None


def read_worker_state(path: Path) -> dict:
    """Worker r > 0's ``worker-r.pt`` (its RNG states), or one clear error."""
    if not path.exists():
        raise HydoError(f"{path} is missing: this run's worker state cannot be resumed")
    state = load_checkpoint(path)
    if int(state.get("format", -1)) != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path}: worker state format {state.get('format')} != {CHECKPOINT_FORMAT}")
    return state


def _worker_main(
    cfg: dict, run_dir: str, resume: bool, rank: int, spec: GroupSpec, fresh_replay: bool
) -> None:
    """Entry point of worker ``rank`` > 0 (a spawned process): same loop, no logs or evaluation."""
    _die_with_parent()
    group = WorkerGroup(rank, spec)
    try:
        trainer = Trainer(
            TrainConfig(**cfg), Path(run_dir), resume=resume, rank=rank, fresh_replay=fresh_replay
        )
        trainer.group = group
        trainer._train()
    except BaseException:
        group.abort()
        traceback.print_exc()
        sys.stderr.flush()
        os._exit(1)


def _die_with_parent() -> None:
    """Linux: SIGKILL this worker when worker 0 dies, so an orphan never writes its shard into a
    folder that a resumed run is already using."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    pr_set_pdeathsig = 1
    try:
        ctypes.CDLL("libc.so.6").prctl(pr_set_pdeathsig, signal.SIGKILL)
    except (OSError, AttributeError):
        pass
    if os.getppid() == 1:  # worker 0 died before the call above
        os._exit(1)


def _watch_workers(workers: list, done: threading.Event) -> None:
    """Worker 0's watchdog: a worker that dies (a crash, the OOM killer) would leave worker 0 waiting
    at the next collective for the group's timeout. Stop the run at once instead; the last
    checkpoint stays valid (atomic writes)."""
    while not done.wait(1.0):
        for w in workers:
            if not w.is_alive() and w.exitcode not in (0, None):
                print(
                    f"error: training worker {w.name} died (exit code {w.exitcode}); "
                    "the run stopped at its last checkpoint: resume it with `hydo train --resume`",
                    file=sys.stderr,
                )
                os._exit(1)
