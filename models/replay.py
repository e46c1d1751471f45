"""Replay buffer for hybrid (location, motion) transitions, Stable-Baselines3 style.

Preallocated numpy arrays at fixed point counts; observations stored as float16 (0.24 mm resolution
at 0.5 m, far below the sensors' noise) which halves memory against float32; motions in [-1, 1];
``terminated`` kept apart from ``truncated`` so that hitting the primitive cap still bootstraps.
Sampling returns a :class:`ReplayBatch` of float32 torch tensors.

Hindsight relabelling (Andrychowicz et al. 2017, HER's "future" strategy): when the caller also
stores each transition's goal pose and the object pose it reached, ``sample(..., relabel_future=f)``
gives a fraction ``f`` of the batch the goal "the pose the object had after this or a later primitive
of the same episode" instead of the episode's own. The goal only enters the observation through the
goal flow, so the new flow follows from the stored one without the object's mesh: the point ``p``
with flow ``φ`` sits at ``q = p + φ`` in the old goal pose ``G``, so for a new goal ``G'``::

    φ' = G' · G⁻¹ · q − p          (object points; background flow stays 0)

and the reward and success are recomputed from ``φ'`` of the next observation. ``G`` is the pose the
observation's flow points to, stored per observation: for a symmetric object the env points the
flow to the nearest pose that looks like the goal, which may differ between an observation and the
next. The relabelled goal is treated the same way: with the object's symmetries ``S`` (given per
object id, :attr:`ReplayBuffer.symmetries`), ``G'`` is, per observation, the one of the poses
``A·S_k`` that look like the pose reached ``A`` whose flow is smallest over the observed points, so a
cylinder that rolled on its way is not asked to roll back.
Every transition then also teaches the critic what its push actually did, near the goal as much as
far from it.

Memory (N = N_obj + N_bg points): two clouds of ``N × (3 + 4)`` float16 and their object normals
``N_obj × 3`` float16 per transition, plus the three poses (3 × 4 float32 each), the object id and an episode link,
i.e. ``28·N + 12·N_obj + 173`` bytes; 128 + 128 points → 8.9 kB, 200k transitions → 1.65 GiB.

Resume: :meth:`save` / :meth:`load` write the filled part and the sampling RNG state to one ``.npz``
(atomically), so a resumed run samples exactly what it would have sampled. A full shard is ~0.9 GB
and took 5–11 s to write here, at every checkpoint; so a training run writes one snapshot, then
only what each checkpoint interval added (:meth:`save_segment`: ~1 % of that), and a new snapshot
once the segments since the last one hold a capacity's worth. :meth:`apply_segment` replays a
segment onto a loaded snapshot, exactly.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from sim.atomic import atomic_write
from sim.contract import FEATURE_DIM


class ReplayBatch(NamedTuple):
    """A minibatch of transitions; all float32 unless noted, on the buffer's device."""

    points: torch.Tensor  # (B, N, 3) metres, world frame, object points first
    features: torch.Tensor  # (B, N, 4) [is_object, goal_flow_xyz (m)]
    index: torch.Tensor  # (B,) int64 in [0, N_obj): the chosen object point
    motion: torch.Tensor  # (B, 3) in [-1, 1]
    reward: torch.Tensor  # (B,)
    next_points: torch.Tensor  # (B, N, 3)
    next_features: torch.Tensor  # (B, N, 4)
    terminated: torch.Tensor  # (B,) 1.0 where the episode ended by success / failure (no bootstrap)
    truncated: torch.Tensor  # (B,) 1.0 where it hit the primitive cap (still bootstraps)
    normals: torch.Tensor | None = None  # (B, N_obj, 3) unit outward normals of the object points
    next_normals: torch.Tensor | None = None  # (B, N_obj, 3)
    discount: torch.Tensor | None = None  # (B,) γ^m of an m-primitive return (n-step); None: γ


class Transition(NamedTuple):
    """What the trainer hands the replay: one transition (``points (N, 3)`` …) or ``E`` of them stacked
    on a leading axis (``points (E, N, 3)`` …), numpy arrays.

    ``points``/``features`` are the observation the action was taken in; ``next_*`` the real next
    observation even when the episode was truncated (the bootstrap needs it). ``normals`` /
    ``next_normals`` ``(E, N_obj, 3)``: the object points' normals of both (stored as zeros when not
    given; an encoder with ``encoder_normals`` needs them). For hindsight relabelling also give
    ``goal_T (E, 4, 4)``, the goal pose the observation's flow points to, and ``achieved_T (E, 4, 4)``,
    the object pose after the primitive (world transforms); and ``next_goal_T (E, 4, 4)``, the goal
    of the next observation's flow, where it may differ: the env points the flow to the nearest
    pose that looks like the goal (``sim.env``'s symmetric goals), which can change with the object's
    pose. Without it the next observation's goal is ``goal_T``. ``object_id (E,)``: which object
    (its row in :attr:`ReplayBuffer.symmetries`), so that a relabelled goal is reached up to its
    symmetry too; without it the relabelled goal is the exact pose reached.
    """

    points: np.ndarray  # (E, N, 3) metres, world frame, object points first
    features: np.ndarray  # (E, N, 4) [is_object, goal_flow_xyz (m)]
    index: np.ndarray | int  # (E,) in [0, N_obj): the chosen object point
    motion: np.ndarray  # (E, 3) in [-1, 1]
    reward: np.ndarray | float  # (E,)
    next_points: np.ndarray  # (E, N, 3)
    next_features: np.ndarray  # (E, N, 4)
    terminated: np.ndarray | bool  # (E,) ended by success / failure (no bootstrap)
    truncated: np.ndarray | bool  # (E,) hit the primitive cap (still bootstraps)
    goal_T: np.ndarray | None = None  # (E, 4, 4)
    achieved_T: np.ndarray | None = None  # (E, 4, 4)
    normals: np.ndarray | None = None  # (E, N_obj, 3)
    next_normals: np.ndarray | None = None  # (E, N_obj, 3)
    next_goal_T: np.ndarray | None = None  # (E, 4, 4); None: goal_T
    object_id: np.ndarray | int | None = None  # (E,) the object's row in ReplayBuffer.symmetries


def _available_memory_bytes() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_AVPHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return None


#: Arrays ``ReplayBuffer.save`` writes beside ``meta`` and ``rng``; the first nine are in every
#: replay.npz, the normal and pose arrays only in those written since they were added (older replays
#: load with them zero; a zero ``next_goal_T`` reads as ``goal_T``).
SAVED_ARRAYS = (
    "points",
    "features",
    "index",
    "motion",
    "reward",
    "next_points",
    "next_features",
    "terminated",
    "truncated",
    "normals",
    "next_normals",
    "goal_T",
    "achieved_T",
    "has_poses",
    "next_goal_T",
    "object_id",
    "next_slot",
)
REQUIRED_ARRAYS = ("meta", "rng", *SAVED_ARRAYS[:9])
#: A segment (:meth:`ReplayBuffer.save_segment`) holds ``slots`` and every saved array at those
#: slots, except ``next_slot``, which it holds whole (a new transition links the episode's previous
#: one, which may sit in an older segment). ``next_goal_T`` and ``object_id`` came later: segments
#: written before them lack them (those slots read ``goal_T`` and no object: exact relabelled goals).
SEGMENT_OPTIONAL = ("next_goal_T", "object_id")
SEGMENT_ARRAYS = (
    "meta",
    "rng",
    "slots",
    "streams",
    "next_slot",
    *(k for k in SAVED_ARRAYS[:-1] if k not in SEGMENT_OPTIONAL),
)


class ReplayBuffer:
    """Fixed-capacity FIFO of transitions at ``N = n_obj + n_bg`` points.

    Args:
        capacity: transitions kept; the oldest is overwritten when full.
        n_obj: object points per cloud.
        n_bg: background points per cloud.
        seed: seed of the sampling RNG (``numpy.random.Generator``).
        device: torch device of sampled batches.
        success_threshold: mean goal-flow norm (metres) under which a relabelled goal counts as
            reached (the env's contract; only hindsight relabelling uses it).
    """

    def __init__(
        self,
        capacity: int,
        n_obj: int,
        n_bg: int,
        seed: int = 0,
        device: str = "cpu",
        success_threshold: float = 0.03,
    ) -> None:
        if capacity < 1:
            raise ValueError(f"`capacity` must be ≥ 1. Got {capacity}.")
        self.capacity, self.n_obj, self.n_bg = capacity, n_obj, n_bg
        self.success_threshold = success_threshold
        self.n_points = n_obj + n_bg
        self.device = torch.device(device)
        self.rng = np.random.default_rng(seed)
        self.pos, self.full = 0, False
        need = self.capacity * self.bytes_per_transition
        avail = _available_memory_bytes()
        if avail is not None and need > avail:
            warnings.warn(
                f"replay buffer needs {need / 2**30:.2f} GiB for {capacity} transitions at "
                f"N={self.n_points} points but only {avail / 2**30:.2f} GiB is available",
                ResourceWarning,
                stacklevel=2,
            )
        c, n = capacity, self.n_points
        self.points = np.zeros((c, n, 3), dtype=np.float16)
        self.features = np.zeros((c, n, FEATURE_DIM), dtype=np.float16)
        self.next_points = np.zeros((c, n, 3), dtype=np.float16)
        self.next_features = np.zeros((c, n, FEATURE_DIM), dtype=np.float16)
        self.normals = np.zeros((c, n_obj, 3), dtype=np.float16)  # the encoder may take them
        self.next_normals = np.zeros((c, n_obj, 3), dtype=np.float16)
        self.index = np.zeros((c,), dtype=np.int32)
        self.motion = np.zeros((c, 3), dtype=np.float32)
        self.reward = np.zeros((c,), dtype=np.float32)
        self.terminated = np.zeros((c,), dtype=np.bool_)
        self.truncated = np.zeros((c,), dtype=np.bool_)
        # hindsight relabelling: the goal pose in force and the object pose reached after the
        # primitive (rows 0-2 of the world transforms), and the slot of the episode's next transition
        self.goal_T = np.zeros((c, 3, 4), dtype=np.float32)
        self.achieved_T = np.zeros((c, 3, 4), dtype=np.float32)
        self.next_goal_T = np.zeros((c, 3, 4), dtype=np.float32)  # all zero: the same as goal_T
        self.has_poses = np.zeros((c,), dtype=np.bool_)
        self.object_id = np.full((c,), -1, dtype=np.int16)  # -1: not given (old replays)
        #: Per object id, the object's symmetry transforms ``(S, 4, 4)`` (object frame, identity first,
        #: ``sim.symmetry.symmetries``). Not saved: the trainer sets it from the run's object set, whose
        #: order fixes the ids. Empty: relabelled goals are the exact poses reached.
        self.symmetries: tuple[np.ndarray, ...] = ()
        self._symmetry_cache: tuple | None = None  # (symmetries, counts, padded): _symmetry_table
        self.next_slot = np.full((c,), -1, dtype=np.int32)
        self._last_slot: dict[int, int] = {}  # stream (env) id → its latest slot, while its episode runs
        self.unsaved = 0  # transitions added since the last save / save_segment / load (≤ capacity)
        self.snapshot_seq: int | None = None  # ``seq`` of the snapshot this buffer was loaded from

    @property
    def bytes_per_transition(self) -> int:
        """Bytes one stored transition occupies (both clouds and their normals float16, action,
        reward, flags, relabelling poses)."""
        cloud = self.n_points * (3 + FEATURE_DIM) * 2 + self.n_obj * 3 * 2  # float16
        poses = 3 * 12 * 4 + 1 + 2 + 4  # goal_T, achieved_T, next_goal_T, has_poses, object_id, next_slot
        return 2 * cloud + 4 + 3 * 4 + 4 + 1 + 1 + poses

    @property
    def nbytes(self) -> int:
        """Bytes preallocated for the whole capacity."""
        return self.capacity * self.bytes_per_transition

    def __len__(self) -> int:
        return self.capacity if self.full else self.pos

    def add(self, transition: Transition) -> None:
        """Store one :class:`Transition` or a batch of them.

        For hindsight relabelling, row ``k`` of a batch is read as the next primitive of stream (env)
        ``k``: consecutive rows of one stream are linked until one ends its episode (terminated or
        truncated), so add every env's transition in the same order at each step.
        """
        (points, features, index, motion, reward, next_points, next_features, terminated, truncated,
         goal_T, achieved_T, normals, next_normals, next_goal_T, object_id) = transition  # fmt: skip
        points = np.asarray(points)
        single = points.ndim == 2
        cols = [points, features, index, motion, reward, next_points, next_features, terminated, truncated]
        cols = [np.asarray(x)[None] if single else np.asarray(x) for x in cols]
        e = cols[0].shape[0]
        n = self.n_points
        shapes = {
            "points": (e, n, 3),
            "features": (e, n, FEATURE_DIM),
            "index": (e,),
            "motion": (e, 3),
            "reward": (e,),
            "next_points": (e, n, 3),
            "next_features": (e, n, FEATURE_DIM),
            "terminated": (e,),
            "truncated": (e,),
        }
        for (name, shape), x in zip(shapes.items(), cols, strict=True):
            if x.shape != shape:
                raise ValueError(f"`{name}` must have shape {shape}. Got {x.shape}.")
        idx = cols[2]
        if np.any(idx < 0) or np.any(idx >= self.n_obj):
            raise ValueError(f"`index` must be in [0, {self.n_obj}). Got {idx}.")
        if np.any(np.abs(cols[3]) > 1.0):
            raise ValueError("`motion` must lie in [-1, 1].")
        slots = (self.pos + np.arange(e)) % self.capacity
        for name, x in zip(shapes, cols, strict=True):
            getattr(self, name)[slots] = x
        self.next_slot[slots] = -1
        for name, x in (("normals", normals), ("next_normals", next_normals)):
            if x is None:
                getattr(self, name)[slots] = 0.0
                continue
            x = np.asarray(x).reshape((e, -1, 3))
            if x.shape != (e, self.n_obj, 3):
                raise ValueError(f"`{name}` must have shape {(e, self.n_obj, 3)}. Got {x.shape}.")
            getattr(self, name)[slots] = x
        if (goal_T is None) != (achieved_T is None):
            raise ValueError("pass both `goal_T` and `achieved_T`, or neither")
        if goal_T is None:
            self.has_poses[slots] = False
            self._last_slot.clear()
        else:
            goal_T, achieved_T = (np.asarray(x).reshape(e, 4, 4)[:, :3] for x in (goal_T, achieved_T))
            self.goal_T[slots], self.achieved_T[slots] = goal_T, achieved_T
            self.next_goal_T[slots] = (
                0.0 if next_goal_T is None else np.asarray(next_goal_T).reshape(e, 4, 4)[:, :3]
            )
            self.has_poses[slots] = True
            self.object_id[slots] = -1 if object_id is None else np.asarray(object_id).reshape(e)
            ended = cols[7] | cols[8]
            for k, slot in enumerate(slots.tolist()):
                prev = self._last_slot.pop(k, None)
                if prev is not None:
                    self.next_slot[prev] = slot
                if not ended[k]:
                    self._last_slot[k] = slot
        self.full = self.full or self.pos + e >= self.capacity
        self.pos = int((self.pos + e) % self.capacity)
        self.unsaved = min(self.unsaved + e, self.capacity)

    def rewind(self, pos: int, full: bool) -> None:
        """Back to the state a checkpoint recorded (``pos``, ``full``): forget what was added after it,
        and end every episode in flight (a resumed run restarts them, so no hindsight goal links an
        episode to the next one). A shard saved just after its checkpoint is at most one checkpoint
        interval ahead; its extra slots stay in memory but are never linked again."""
        ahead = (self.pos - pos) % self.capacity if (self.full or self.pos >= pos) else 0
        dropped = (pos + np.arange(ahead)) % self.capacity
        if len(dropped):
            self.next_slot[dropped] = -1
            self.next_slot[np.isin(self.next_slot, dropped)] = -1
        self.pos, self.full = int(pos), bool(full)
        self.unsaved = max(0, self.unsaved - ahead)
        self.end_episodes()

    def end_episodes(self) -> None:
        """End every episode in flight: each stream's next transition starts a new one, so no
        hindsight goal or n-step return links across (a resume, or an evaluation that played its own
        episodes on the training envs)."""
        self._last_slot.clear()

    def sample(
        self, batch_size: int, relabel_future: float = 0.0, n_step: int = 1, gamma: float = 0.99
    ) -> ReplayBatch:
        """Uniformly sample ``batch_size`` stored transitions (with replacement across calls).

        ``relabel_future = f`` relabels about a fraction ``f`` of them (those stored with poses) with a
        goal reached later in their episode (:meth:`relabel`).

        ``n_step = n > 1``: each transition that is not relabelled carries the return of up to ``n``
        primitives of its episode, ``Σ_{k<m} γ^k r_{t+k}``, the next observation and ``terminated``
        of primitive ``t+m−1`` and ``discount = γ^m`` (:meth:`n_step_chain`), so the critic's target
        reaches ``m`` primitives back in one update. Relabelled transitions stay one-step (their goal
        is not the one their later rewards were paid for).
        """
        if len(self) == 0:
            raise ValueError("cannot sample from an empty replay buffer")
        if not 0.0 <= relabel_future <= 1.0:
            raise ValueError(f"`relabel_future` must be in [0, 1]. Got {relabel_future}.")
        if n_step < 1:
            raise ValueError(f"`n_step` must be ≥ 1. Got {n_step}.")
        i = self.rng.integers(0, len(self), size=batch_size)
        rows = np.zeros(0, dtype=np.int64)
        if relabel_future > 0.0:
            pick = (self.rng.random(batch_size) < relabel_future) & self.has_poses[i]
            rows = np.flatnonzero(pick)
        last, reward, steps = i, self.reward[i], None  # one primitive each
        if n_step > 1:
            one_step = np.zeros(batch_size, dtype=np.bool_)
            one_step[rows] = True
            last, reward, steps = self.n_step_chain(i, n_step, gamma, one_step)
        cols = {
            "points": self.points[i].astype(np.float32),
            "features": self.features[i].astype(np.float32),
            "next_points": self.next_points[last].astype(np.float32),
            "next_features": self.next_features[last].astype(np.float32),
            "reward": np.array(reward, dtype=np.float32),
            "terminated": self.terminated[last],
        }
        if rows.size:
            self.relabel(i[rows], rows, cols)

        def t(x: np.ndarray, dtype=torch.float32) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(x)).to(device=self.device, dtype=dtype)

        return ReplayBatch(
            points=t(cols["points"]),
            features=t(cols["features"]),
            index=t(self.index[i], torch.int64),
            motion=t(self.motion[i]),
            reward=t(cols["reward"]),
            next_points=t(cols["next_points"]),
            next_features=t(cols["next_features"]),
            terminated=t(cols["terminated"]),
            truncated=t(self.truncated[last]),
            normals=t(self.normals[i]),
            next_normals=t(self.next_normals[last]),
            discount=None if steps is None else t(gamma ** steps.astype(np.float64)),
        )

    def n_step_chain(
        self, slots: np.ndarray, n: int, gamma: float, one_step: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Follow each slot (S,) up to ``n − 1`` primitives on along its episode's links.

        Returns ``(last (S,) int, ret (S,) float64, m (S,) int)``: the slot of the last primitive
        taken, ``Σ_{k<m} γ^k r`` over the ``m`` primitives and ``m`` (1 … n). A chain stops early at
        the episode's end (a terminated or truncated primitive has no link), at a transition stored
        without poses (no link either), and where ``one_step`` is set. The intermediate primitives'
        entropy terms are left out of the return, as n-step SAC implementations do: the bootstrap
        at the end carries the soft value.
        """
        slots = np.asarray(slots, dtype=np.int64)
        cur = slots.copy()
        ret = self.reward[cur].astype(np.float64)
        m = np.ones(slots.shape, dtype=np.int64)
        live = np.ones(slots.shape, dtype=np.bool_) if one_step is None else ~np.asarray(one_step)
        for k in range(1, n):
            nxt = self.next_slot[cur]
            live &= nxt >= 0
            if not live.any():
                break
            cur = np.where(live, nxt, cur)
            ret += np.where(live, gamma**k * self.reward[cur], 0.0)
            m += live
        return cur, ret, m

    def future_slots(self, slots: np.ndarray) -> np.ndarray:
        """For each slot (S,), a uniformly drawn slot of the same episode at or after it (S,) int.

        Follows the episode links: an episode has at most a few dozen primitives, so this is a few
        vectorised hops, never a per-transition Python loop."""
        slots = np.asarray(slots, dtype=np.int64)
        remaining = np.zeros_like(slots)  # transitions after each slot in its episode, so far stored
        cur = slots.copy()
        for _ in range(self.capacity):
            nxt = self.next_slot[cur]
            live = nxt >= 0
            if not live.any():
                break
            remaining += live
            cur = np.where(live, nxt, cur)
        hops = np.floor(self.rng.random(slots.shape) * (remaining + 1)).astype(np.int64)
        out = slots.copy()
        for _ in range(int(hops.max(initial=0))):
            step = hops > 0
            out = np.where(step, self.next_slot[out], out)
            hops -= step
        return out

    def relabel(self, slots: np.ndarray, rows: np.ndarray, cols: dict[str, np.ndarray]) -> None:
        """Replace, in place, the goal of batch ``rows`` (stored at ``slots``) by a future achieved pose.

        ``cols`` holds the batch's float32 ``points``/``features``/``next_points``/``next_features``
        (B, N, ·), ``reward`` (B,) and ``terminated`` (B,). The new reward is ``−mean ‖φ'‖`` over the
        next observation's object points (the env averages over the whole surface: a sampling
        difference of a few per cent), and a transition is terminated exactly when it reaches the new
        goal. (A transition that ended its episode, by success or by the object leaving the bin, has
        only itself as future, so it always reaches its relabelled goal.)
        """
        new_goal = np.zeros((len(slots), 4, 4), dtype=np.float64)
        new_goal[:, :3] = self.achieved_T[self.future_slots(slots)]
        new_goal[:, 3, 3] = 1.0
        old_goal = np.zeros_like(new_goal)
        old_goal[:, :3] = self.goal_T[slots]
        old_goal[:, 3, 3] = 1.0
        next_goal = old_goal.copy()  # the next observation's flow may point to another symmetric pose
        stored = self.next_goal_T[slots]
        given = np.any(stored != 0.0, axis=(1, 2))
        next_goal[given, :3] = stored[given]
        n = self.n_obj
        for (pts, feat), goal in (
            (("points", "features"), old_goal),
            (("next_points", "next_features"), next_goal),
        ):
            target = self._nearest_symmetric(
                new_goal, goal, slots, cols[pts][rows, :n], cols[feat][rows, :n, 1:]
            )
            rel = target @ np.linalg.inv(goal)  # (S, 4, 4): the flow's goal pose → the new goal pose
            p = cols[pts][rows, :n].astype(np.float64)  # (S, n_obj, 3)
            q = p + cols[feat][rows, :n, 1:]  # where each point sits in the old goal pose
            moved = q @ rel[:, :3, :3].transpose(0, 2, 1) + rel[:, None, :3, 3]
            cols[feat][rows, :n, 1:] = (moved - p).astype(np.float32)
        distance = np.linalg.norm(cols["next_features"][rows, :n, 1:], axis=-1).mean(axis=1)
        cols["reward"][rows] = -distance
        cols["terminated"][rows] = distance < self.success_threshold

    def _nearest_symmetric(
        self, new_goal: np.ndarray, goal: np.ndarray, slots: np.ndarray, points: np.ndarray, flow: np.ndarray
    ) -> np.ndarray:
        """Per relabelled row, the pose among ``new_goal · S_k`` (the object's symmetries) that the
        env would point this observation's flow to: the smallest mean flow over its object points.

        ``new_goal`` / ``goal`` (S, 4, 4): the relabelled goal and the goal the stored flow points to;
        ``points`` / ``flow`` (S, n_obj, 3) float32: the observation's object points and stored flow.
        A point sits at ``q = p + φ`` in ``goal``, so under ``new_goal · S_k`` it goes to
        ``new_goal · S_k · goal⁻¹ · q``. Rows without an object id (or with no symmetry) keep ``new_goal``.
        Returns (S, 4, 4)."""
        out = new_goal.copy()
        if not self.symmetries:
            return out
        ids = self.object_id[slots]
        counts, padded = self._symmetry_table()
        sel = np.flatnonzero((ids >= 0) & (counts[np.maximum(ids, 0)] > 1))
        if not len(sel):
            return out
        # One pass over every relabelled row of every symmetric object: each row's symmetries padded
        # to the longest with its identity (a repeated candidate cannot win an argmin over the first).
        # On 6D runs with relabelling this search was ~17 % of a worker's time as a per-object einsum.
        sym = padded[ids[sel]]  # (s, K, 4, 4)
        p = points[sel].astype(np.float64)  # (s, n, 3)
        q = p + flow[sel]  # where each point sits in `goal`
        cand = new_goal[sel, None] @ sym  # (s, K, 4, 4)
        rel = cand @ np.linalg.inv(goal[sel])[:, None]  # (s, K, 4, 4)
        # ‖R_k q_i + t_k − p_i‖² expanded, so that every (point, candidate) pair comes from one
        # (s, n, 15) @ (s, 15, K) matmul instead of an (s, n, K, 3) tensor reduced over its last axis:
        # ‖q‖² + ‖p‖² + ‖t‖² + 2 q·Rᵀt − 2 Σ_ab R_ab p_a q_b − 2 p·t.
        rot, t = rel[..., :3, :3], rel[..., :3, 3]  # (s, K, 3, 3), (s, K, 3)
        outer = p[..., :, None] * q[..., None, :]  # (s, n, 3, 3): p_a q_b
        lhs = np.concatenate([q, -outer.reshape(*p.shape[:2], 9), -p], axis=-1)  # (s, n, 15)
        rhs = np.concatenate(
            [np.einsum("skab,ska->skb", rot, t), rot.reshape(*rot.shape[:2], 9), t], axis=-1
        )  # (s, K, 15)
        sq = 2.0 * (lhs @ rhs.transpose(0, 2, 1))  # (s, n, K)
        sq += ((q * q).sum(-1) + (p * p).sum(-1))[..., None] + (t * t).sum(-1)[:, None]
        cost = np.sqrt(np.maximum(sq, 0.0)).mean(1)  # (s, K) mean flow
        out[sel] = cand[np.arange(len(sel)), cost.argmin(1)]
        return out

    def _symmetry_table(self) -> tuple[np.ndarray, np.ndarray]:
        """``symmetries`` as arrays: per object id its count ``(n_objects,)`` and its transforms padded
        with its identity (row 0) to the longest, ``(n_objects, K_max, 4, 4)``; rebuilt when the
        trainer assigns another tuple."""
        if self._symmetry_cache is None or self._symmetry_cache[0] is not self.symmetries:
            counts = np.array([len(sym) for sym in self.symmetries], dtype=np.int64)
            padded = np.empty((len(self.symmetries), int(counts.max(initial=1)), 4, 4))
            for i, sym in enumerate(self.symmetries):
                padded[i] = sym[0]
                padded[i, : len(sym)] = sym
            self._symmetry_cache = (self.symmetries, counts, padded)
        return self._symmetry_cache[1], self._symmetry_cache[2]

    _ARRAYS = SAVED_ARRAYS

    def _state_arrays(self) -> dict[str, np.ndarray]:
        """``meta``, ``rng`` and ``streams``: what a snapshot and a segment both end on."""
        return {
            "meta": np.array(
                [self.capacity, self.n_obj, self.n_bg, self.pos, int(self.full)], dtype=np.int64
            ),
            "rng": np.frombuffer(repr(self.rng.bit_generator.state).encode(), dtype=np.uint8),
            "streams": np.array(sorted(self._last_slot.items()), dtype=np.int64).reshape(-1, 2),
        }

    def save(self, path: str | os.PathLike, seq: int | None = None) -> None:
        """Write the stored transitions and the RNG state to ``path`` (``.npz``), atomically.

        ``seq``: the number of the training run's save this snapshot is (recorded as ``seq``, so a
        loader knows which segments it already contains)."""
        path = Path(path)
        n = len(self)
        arrays = {k: getattr(self, k)[:n] for k in self._ARRAYS}
        extra = {} if seq is None else {"seq": np.array(seq, dtype=np.int64)}
        state = self._state_arrays()
        atomic_write(
            path, lambda f: np.savez(f, threshold=self.success_threshold, **state, **extra, **arrays)
        )
        self.unsaved = 0

    def save_segment(self, path: str | os.PathLike) -> int:
        """Write what was added since the last save (the ``unsaved`` slots before ``pos``), the whole
        ``next_slot`` and the RNG state to ``path`` (``.npz``), atomically. Returns the transitions
        written. Applying it (:meth:`apply_segment`) to the buffer as it was at the last save gives
        this buffer exactly."""
        slots = (self.pos - self.unsaved + np.arange(self.unsaved)) % self.capacity
        arrays = {k: getattr(self, k)[slots] for k in self._ARRAYS if k != "next_slot"}
        state = self._state_arrays()
        atomic_write(
            Path(path),
            lambda f: np.savez(f, slots=slots.astype(np.int64), next_slot=self.next_slot, **state, **arrays),
        )
        written, self.unsaved = self.unsaved, 0
        return written

    def apply_segment(self, arrays: dict[str, np.ndarray]) -> None:
        """Replay a segment's arrays (read from a :meth:`save_segment` file) onto this buffer."""
        import ast

        slots = arrays["slots"]
        for k in self._ARRAYS:
            if k != "next_slot" and k in arrays:
                getattr(self, k)[slots] = arrays[k]
        self.next_slot[:] = arrays["next_slot"]
        _, _, _, pos, full = (int(v) for v in arrays["meta"])
        self.pos, self.full = pos, bool(full)
        self._last_slot = {int(k): int(v) for k, v in arrays["streams"]}
        self.rng.bit_generator.state = ast.literal_eval(bytes(arrays["rng"]).decode())
        self.unsaved = 0

    @classmethod
    def load(cls, path: str | os.PathLike, device: str = "cpu") -> ReplayBuffer:
        """Rebuild a buffer written by :meth:`save` (same capacity, contents and RNG state)."""
        with np.load(path) as data:
            return cls.from_arrays(data, device=device)

    @classmethod
    def from_arrays(cls, data, device: str = "cpu") -> ReplayBuffer:
        """Rebuild a buffer from a :meth:`save` file's members (an open ``NpzFile`` or a dict of them)."""
        import ast

        capacity, n_obj, n_bg, pos, full = (int(v) for v in data["meta"])
        threshold = float(data["threshold"]) if "threshold" in data else 0.03
        buf = cls(capacity, n_obj, n_bg, device=device, success_threshold=threshold)
        n = data["points"].shape[0]
        for k in cls._ARRAYS:
            if k in data:  # older replays lack the pose (and normal) arrays
                getattr(buf, k)[:n] = data[k]
        if "streams" in data:
            buf._last_slot = {int(k): int(v) for k, v in data["streams"]}
        buf.pos, buf.full = pos, bool(full)
        buf.rng.bit_generator.state = ast.literal_eval(bytes(data["rng"]).decode())
        buf.snapshot_seq = int(data["seq"]) if "seq" in data else None
        return buf
