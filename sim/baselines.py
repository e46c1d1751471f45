"""Scripted policies that prove the env is sound: ``random`` and ``heuristic``.

Both take one observation (``sim.contract`` layout) and return an env action ``(index, motion)``.
"""

from __future__ import annotations

import numpy as np

from sim.primitive import N_PUSH_STEPS, PUSH_STEP_M, FeasibilityMask

PUSH_REACH_M = N_PUSH_STEPS * PUSH_STEP_M  # a full-scale motion moves the fingertip 9 cm
PALM_CLEARANCE_M = 0.04  # contact at most this far below the object top keeps the palm (4.6 cm up) clear


def random_action(obs: dict[str, np.ndarray], rng: np.random.Generator) -> tuple[int, np.ndarray]:
    """Uniform contact point among the object points and uniform motion in [-1, 1]^3."""
    n_obj = len(obs["normals"])
    return int(rng.integers(n_obj)), rng.uniform(-1.0, 1.0, 3).astype(np.float32)


def heuristic_action(
    obs: dict[str, np.ndarray], rng: np.random.Generator, feasible: FeasibilityMask | None = None
) -> tuple[int, np.ndarray]:
    """Push from the point whose normal best opposes the mean goal flow, along that flow.

    Among object points whose normal opposes the horizontal flow direction (cosine < -0.7), take
    the lowest one high enough that the palm, 5.4 cm above the fingertip, clears the object's top
    (pushing low slides rather than tips the object); the push covers the mean flow's horizontal
    length, capped at the primitive's 9 cm reach. ``feasible`` is the feasibility mask the learned
    policies choose under (``sim.primitive.feasibility_mask`` for this observation as a batch of
    one): only points whose push can run are candidates, so the baseline does not waste primitives
    the simulator refuses.
    """
    n_obj = len(obs["normals"])
    flow = obs["features"][:n_obj, 1:4]
    points, normals = obs["points"][:n_obj], obs["normals"]
    mean_flow = flow.mean(axis=0)
    horizontal = np.array([mean_flow[0], mean_flow[1], 0.0])
    length = np.linalg.norm(horizontal)
    if length < 1e-6:
        return random_action(obs, rng)
    direction = horizontal / length
    motion = (direction * min(length / PUSH_REACH_M, 1.0)).astype(np.float32)
    allowed = np.ones(n_obj, dtype=bool)
    if feasible is not None:  # the same motion at every point: one mask call
        allowed = np.asarray(feasible(np.broadcast_to(motion, (1, n_obj, 3))))[0]
    cosine = np.where(allowed, normals @ direction, np.inf)
    candidates = np.flatnonzero(cosine < -0.7)
    if len(candidates) == 0:
        candidates = np.array([int(np.argmin(cosine))])
    height = points[candidates, 2]
    reachable = height >= points[:, 2].max() - PALM_CLEARANCE_M
    pool = candidates[reachable] if np.any(reachable) else candidates[[int(np.argmax(height))]]
    # a random one of the lowest quarter of the reachable candidates: random, so that a push the
    # env refused (e.g. the palm would start inside a wall) is not repeated forever
    pool = pool[np.argsort(points[pool, 2])[: max(1, len(pool) // 4)]]
    index = int(rng.choice(pool))
    return index, motion


POLICIES = {"random": random_action, "heuristic": heuristic_action}
