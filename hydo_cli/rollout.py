"""Running episodes: shared by ``hydo eval``, ``hydo train``'s periodic evaluation and the benches.

A *policy* here is a function from a list of observations (one per env) to a list of env actions
``(index, motion)``, so torch agents can batch the decision and scripted baselines map over it.
Episode ``i`` of a run with seed ``s`` always resets with seed ``s * 1_000_003 + i``: every policy
evaluated with the same seed faces the same objects, start poses and goals.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

from sim.goals import episode_seed

Policy = Callable[[list[dict[str, np.ndarray]]], list[tuple[int, np.ndarray]]]


@dataclass
class EpisodeResult:
    object: str
    success: bool
    steps: int  # primitives taken
    episode_return: float
    final_distance: float  # mean goal-flow norm at the end, metres
    rejected: int  # primitives refused (workspace or start collision)
    failure: str  # "" on success, else "object_left_bin" | "timeout"
    behaviour: int | None = None  # behaviour id of a ``sim.tasks`` task episode (None: none / no task)
    start_distance: float = 0.0  # mean goal-flow norm at reset, metres
    goal_tilt_deg: float = 0.0  # how far the goal tilts the object's up direction (~0: move, ≥ 30: flip)
    force_stops: int = 0  # primitives the hand's contact-force stop ended (sim.primitive.FORCE_STOP_N)
    final_tilt_deg: float = 0.0  # the tilt left at the end: a failed flip still ≥ 30 never turned over
    idle: int = 0  # primitives that ran and left the object where it was (sim.env.IDLE_MOVE_M)
    # the distance left at the end split into placing and turning, metres (sim.contract.flow_split);
    # None where the env does not report it
    final_position_m: float | None = None
    final_rotation_m: float | None = None

    def as_dict(self) -> dict:
        return asdict(self)


def run_episodes(
    envs: Sequence,
    policy: Policy,
    n_episodes: int,
    seed: int = 0,
    on_frame: Callable[[int, np.ndarray], None] | None = None,
    on_episode: Callable[[EpisodeResult], None] | None = None,
    shard: tuple[int, int] = (0, 1),
) -> list[EpisodeResult]:
    """Run ``n_episodes`` spread over ``envs`` (stepped in lock-step, one batched decision per step).

    ``on_frame(episode_index, rgb)`` is called after reset and every step when given (video).
    ``shard = (rank, world)`` plays only episodes ``rank, rank + world, …`` of the ``n_episodes``
    (each with the seed it has in the whole set), so ``world`` processes can share one evaluation.
    Results come back in episode order.
    """
    rank, world = shard
    if not 0 <= rank < world:
        raise ValueError(f"`shard` must be (rank, world) with 0 <= rank < world. Got {shard}.")
    results: dict[int, EpisodeResult] = {}
    next_ep = rank
    slots: list[dict | None] = [None] * len(envs)

    def start(k: int) -> None:
        nonlocal next_ep
        if next_ep >= n_episodes:
            slots[k] = None
            return
        obs, info = envs[k].reset(seed=episode_seed(seed, next_ep))
        slots[k] = {
            "ep": next_ep,
            "obs": obs,
            "ret": 0.0,
            "rej": 0,
            "stops": 0,
            "idle": 0,
            "steps": 0,
            "start": info,
        }
        if on_frame is not None:
            on_frame(next_ep, envs[k].render())
        next_ep += world

    for k in range(len(envs)):
        start(k)
    while any(s is not None for s in slots):
        active = [k for k, s in enumerate(slots) if s is not None]
        actions = policy([slots[k]["obs"] for k in active])
        for k, action in zip(active, actions, strict=True):
            s = slots[k]
            obs, reward, terminated, truncated, info = envs[k].step(action)
            s["obs"], s["ret"], s["steps"] = obs, s["ret"] + reward, s["steps"] + 1
            s["rej"] += int(info["rejected"])
            s["stops"] += int(info.get("force_stopped", False))
            s["idle"] += int(info.get("idle", False))
            if on_frame is not None:
                on_frame(s["ep"], envs[k].render())
            if terminated or truncated:
                r = EpisodeResult(
                    object=s["start"]["object"],
                    success=info["success"],
                    steps=s["steps"],
                    episode_return=s["ret"],
                    final_distance=info["distance"],
                    rejected=s["rej"],
                    failure="" if info["success"] else info["failure"],
                    behaviour=info.get("behaviour"),
                    start_distance=s["start"]["distance"],
                    goal_tilt_deg=s["start"].get("goal_tilt_deg", 0.0),
                    force_stops=s["stops"],
                    final_tilt_deg=info.get("goal_tilt_deg", 0.0),
                    idle=s["idle"],
                    final_position_m=info.get("final_position_m"),
                    final_rotation_m=info.get("final_rotation_m"),
                )
                results[s["ep"]] = r
                if on_episode is not None:
                    on_episode(r)
                start(k)
    return [results[i] for i in range(rank, n_episodes, world)]


def summarize(results: Sequence[EpisodeResult]) -> dict:
    """Success rate, mean return, mean steps to success, failure reasons and a per-object breakdown."""
    n = len(results)
    succ = [r for r in results if r.success]
    per_object: dict[str, list[bool]] = {}
    for r in results:
        per_object.setdefault(r.object, []).append(r.success)
    failures: dict[str, int] = {}
    for r in results:
        if not r.success:
            failures[r.failure] = failures.get(r.failure, 0) + 1
    return {
        "episodes": n,
        "success_rate": len(succ) / n if n else 0.0,
        "mean_return": float(np.mean([r.episode_return for r in results])) if n else 0.0,
        "mean_steps_to_success": float(np.mean([r.steps for r in succ])) if succ else None,
        "mean_final_distance_m": float(np.mean([r.final_distance for r in results])) if n else 0.0,
        "rejected_primitives": int(sum(r.rejected for r in results)),
        "failures": failures,
        "per_object": {k: float(np.mean(v)) for k, v in sorted(per_object.items())},
    }


def baseline_policy(name: str, seed: int, feasible_only: bool = True) -> Policy:
    """``random`` or ``heuristic`` from ``sim.baselines`` as a batched policy with its own RNG.

    ``feasible_only``: the heuristic chooses among the points whose push can run, under the same
    feasibility mask as the learned policies (``random`` stays uniform: it is the floor)."""
    from sim.baselines import POLICIES, heuristic_action
    from sim.primitive import feasibility_mask

    act = POLICIES[name]
    rng = np.random.default_rng(seed)
    if act is heuristic_action and feasible_only:
        return lambda observations: [
            heuristic_action(o, rng, feasibility_mask(o["points"][None], o["normals"][None]))
            for o in observations
        ]
    return lambda observations: [act(o, rng) for o in observations]
