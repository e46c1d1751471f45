"""The observation, reward and success contract: its one home.

Training (``sim.env``), export (``models`` via ``hydo_cli.export``) and deploy (``robot``) all import
these names; nothing else defines them. Pure numpy, no MuJoCo, no torch, so the torch-free deploy
path can use it.

Observation (one per decision), all float32, world frame, metres::

    points   (N, 3)       object points first (N_obj), then background points (N_bg)
    features (N, 4)       [is_object, goal_flow_x, goal_flow_y, goal_flow_z]
    normals  (N_obj, 3)   outward unit normals of the object points (the primitive approaches along
                          them; the encoder takes them too when ``AgentConfig.encoder_normals``)

``goal_flow = T_goal · T_obj⁻¹ · p − p`` for object points, 0 for background points.
Reward ``r = −mean_i ‖goal_flow_i‖`` over object points; success when that mean is < 3 cm.

Goals are reached up to the object's symmetry: ``T_goal`` here is :func:`symmetric_goal`'s, the one
of the poses that look exactly like the goal pose (``T_goal · S`` for the object's symmetries ``S``,
``sim.symmetry``) nearest to the current pose. A depth camera cannot see a cylinder's roll about its
axis or tell a box from the box turned 180°, so neither may the task demand it.
"""

from __future__ import annotations

from enum import Enum

import numpy as np

#: Bump when the meaning or layout of an observation changes: exports record it, loaders check it.
OBS_CONTRACT_VERSION = 1

FEATURE_DIM = 4  # [is_object, goal_flow_x, goal_flow_y, goal_flow_z]
SUCCESS_THRESHOLD_M = 0.03  # mean goal-flow norm under which a goal counts as reached (metres)
MAX_PRIMITIVES = 10  # primitives per episode before truncation


class Goals(str, Enum):
    """Goal mode: a planar goal (translation and yaw on the floor) or a 6D stable pose."""

    planar = "planar"
    sixd = "6d"


class ObsSource(str, Enum):
    """Where observations come from: object-mesh surface samples (fast, training) or rendered depth."""

    mesh = "mesh"
    render = "render"


class Contacts(str, Enum):
    """The training scene's contact model (``sim.scene`` says what each sets): the scene's own, or the
    contact settings of HACMan's bin env (the simulator the paper's figures come from)."""

    hydo = "hydo"
    hacman = "hacman"


GOAL_MODES = tuple(g.value for g in Goals)
OBS_SOURCES = tuple(o.value for o in ObsSource)
CONTACT_MODELS = tuple(c.value for c in Contacts)
#: the scene's own contact model: what runs, records and exports made before there was a choice used
CONTACT_DEFAULT = Contacts.hydo.value

#: Default point counts. Chosen by measurement (bench/learner.py): every gradient update is linear in
#: N, and 128 + 128 keeps the planar task learnable while an update stays cheap on 2 CPU cores.
#: HACMan uses 400 + 400. Each run and export records its own counts.
DEFAULT_N_OBJ = 128
DEFAULT_N_BG = 128


def pose_matrix(pos: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """Homogeneous transform (4, 4) from a position (3,) in metres and a unit quaternion (4,) wxyz."""
    w, x, y, z = np.asarray(quat_wxyz, dtype=np.float64) / np.linalg.norm(quat_wxyz)
    T = np.eye(4)
    T[:3, :3] = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    T[:3, 3] = pos
    return T


def transform_points(T: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Apply a (4, 4) transform to points (N, 3)."""
    return p @ T[:3, :3].T + T[:3, 3]


SYMMETRY_PROBE_POINTS = 256  # surface samples that rank the symmetric goals first ...
SYMMETRY_FINALISTS = 4  # ... and the best few, ranked again on all of them


class SymmetricGoals:
    """One goal's symmetric poses, ready to pick from: ``T_goal · S`` for the object's ``symmetries
    (S, 4, 4)`` (object frame, the identity first) and where each puts the surface samples
    ``points_obj (P, 3)`` (object frame). Fixed while the goal is: the env makes one per goal and asks
    :meth:`nearest` in each state; :func:`symmetric_goal` is the one-off form."""

    def __init__(self, T_goal: np.ndarray, points_obj: np.ndarray, symmetries: np.ndarray):
        self.T_goal = T_goal
        self.points_obj = points_obj
        self.n = len(symmetries)
        if self.n <= 1:
            return
        self.goals = T_goal[None] @ symmetries  # (S, 4, 4)
        probe = points_obj[:: max(1, len(points_obj) // SYMMETRY_PROBE_POINTS)]
        self.probe = np.ascontiguousarray(probe, dtype=np.float64)  # as matmul casts it, once
        self._there_probe = self._there(self.goals, self.probe)  # (3, S, P_probe)
        self._there_all: dict[int, np.ndarray] = {}  # finalist -> (3, 1, P), made when first one

    @staticmethod
    def _there(G: np.ndarray, pts: np.ndarray) -> np.ndarray:  # (K, 4, 4), (P, 3) -> (3, K, P)
        """Where the goals ``G`` put the samples ``pts``, coordinate-major: the flows' differences
        then run over contiguous rows."""
        return np.ascontiguousarray((G[:, :3, :3] @ pts.T + G[:, :3, 3:]).transpose(1, 0, 2))

    def nearest(self, T_obj: np.ndarray, points_world: np.ndarray | None = None) -> np.ndarray:
        """The goal pose (4, 4) to use from ``T_obj``: the one whose mean goal flow over the surface
        samples is smallest. Ranked on a strided subset first, then the finalists on all samples.
        ``points_world``: the samples at ``T_obj`` (``transform_points(T_obj, points_obj)``) if the
        caller has them."""
        if self.n <= 1:
            return self.T_goal

        def mean_flow(there: np.ndarray, here: np.ndarray) -> np.ndarray:  # (3, K, P), (3, 1, P) -> (K,)
            # np.linalg.norm(there - here, axis=1).mean(1) of the (K, 3, P) layout bit for bit (the
            # same products and sums in the same order), ~7x faster than norm's middle-axis reduction
            d = there - here
            np.square(d, out=d)
            sq = d[0] + d[1]
            sq += d[2]
            return np.sqrt(sq, out=sq).mean(1)

        # the goal itself (symmetries[0], the identity) is always a finalist: never asked for more than it
        def coordinate_major(points: np.ndarray) -> np.ndarray:  # (P, 3) -> (3, 1, P)
            return np.ascontiguousarray(points.T)[:, None, :]

        here = coordinate_major(transform_points(T_obj, self.probe))
        ranked = np.argsort(mean_flow(self._there_probe, here))
        finalists = sorted({0, *ranked[:SYMMETRY_FINALISTS].tolist()})
        here = coordinate_major(
            transform_points(T_obj, self.points_obj) if points_world is None else points_world
        )
        flows = []
        for k in finalists:  # one at a time: the same flows as one batch, without stacking them
            there = self._there_all.get(k)
            if there is None:
                there = self._there_all[k] = self._there(self.goals[k : k + 1], self.points_obj)
            flows.append(mean_flow(there, here)[0])
        return self.goals[finalists[int(np.argmin(flows))]].copy()


def symmetric_goal(
    T_obj: np.ndarray, T_goal: np.ndarray, points_obj: np.ndarray, symmetries: np.ndarray
) -> np.ndarray:
    """The goal pose (4, 4) to use: of ``T_goal · S`` for the object's ``symmetries (S, 4, 4)``
    (object frame, the identity first), the one whose mean goal flow from ``T_obj`` over the surface
    samples ``points_obj (P, 3)`` (object frame) is smallest. Ranked on a strided subset first, then
    the finalists on all samples (~0.3 ms for a cylinder's 72 symmetries; :class:`SymmetricGoals`
    keeps what depends only on the goal, for picking in many states)."""
    return SymmetricGoals(T_goal, points_obj, symmetries).nearest(T_obj)


def goal_flow(points_world: np.ndarray, T_obj: np.ndarray, T_goal: np.ndarray) -> np.ndarray:
    """Per-point goal flow (N, 3) metres: where each object point must move to reach the goal pose.

    ``points_world`` (N, 3) are object points in the world frame at the current pose ``T_obj``.
    """
    T_rel = T_goal @ np.linalg.inv(T_obj)  # current pose -> goal pose, applied to world points
    return (transform_points(T_rel, points_world) - points_world).astype(np.float32)


def mean_flow_distance(points_world: np.ndarray, T_obj: np.ndarray, T_goal: np.ndarray) -> float:
    """Mean goal-flow norm in metres: the quantity the reward negates and success thresholds."""
    sq = np.square(goal_flow(points_world, T_obj, T_goal))
    # the per-point norms summed as np.linalg.norm(..., axis=1) sums them, without its overhead
    return float(np.sqrt(sq[:, 0] + sq[:, 1] + sq[:, 2]).mean())


def flow_split(points_world: np.ndarray, T_obj: np.ndarray, T_goal: np.ndarray) -> tuple[float, float]:
    """``(position_m, rotation_m)``: the goal flow of object points (N, 3) at ``T_obj`` split into
    what a pure translation would fix and what a turn about the points' centroid would fix, metres.

    ``position_m`` is the norm of the mean flow (how far the centroid is from its place at the goal);
    ``rotation_m`` is the mean norm of the flow left once that is taken out. They bound the success
    metric: ``position_m ≤ mean_flow_distance ≤ position_m + rotation_m``. A failure that ends on the
    goal's face with ``position_m ≥ rotation_m`` ran out of steps placing the object, not turning it.
    """
    flow = goal_flow(points_world, T_obj, T_goal).astype(np.float64)
    shift = flow.mean(axis=0)
    return float(np.linalg.norm(shift)), float(np.linalg.norm(flow - shift, axis=1).mean())


def reward_and_success(points_world, T_obj, T_goal) -> tuple[float, bool, float]:
    """``(reward, success, distance)`` for object points (N, 3) at pose ``T_obj``."""
    d = mean_flow_distance(points_world, T_obj, T_goal)
    return -d, d < SUCCESS_THRESHOLD_M, d


def resample(n_have: int, n_want: int, rng: np.random.Generator) -> np.ndarray:
    """Indices that resample ``n_have`` items to exactly ``n_want`` (without replacement when it can)."""
    if n_have <= 0:
        raise ValueError("cannot resample an empty point set")
    if n_have >= n_want:
        return rng.choice(n_have, n_want, replace=False)
    return np.concatenate([rng.permutation(n_have), rng.choice(n_have, n_want - n_have)])


def build_observation(
    obj_points: np.ndarray,
    obj_normals: np.ndarray,
    bg_points: np.ndarray,
    T_obj: np.ndarray,
    T_goal: np.ndarray,
    n_obj: int,
    n_bg: int,
    rng: np.random.Generator,
) -> dict[str, np.ndarray]:
    """Assemble one observation from segmented clouds (any sizes) at fixed counts ``n_obj + n_bg``.

    obj_points (M, 3), obj_normals (M, 3): visible object points in the world frame at pose
    ``T_obj`` (4, 4); bg_points (L, 3): background (bin, clutter). Random resampling fixes the counts.
    Used by the simulator (mesh and rendered sources) and by deploy alike.
    """
    io = resample(len(obj_points), n_obj, rng)
    ib = resample(len(bg_points), n_bg, rng)
    obj_points, obj_normals, bg_points = (np.asarray(a) for a in (obj_points, obj_normals, bg_points))
    p_obj = obj_points.take(io, axis=0).astype(np.float32)  # take: obj_points[io], faster
    points = np.concatenate([p_obj, bg_points.take(ib, axis=0).astype(np.float32)], axis=0)
    features = np.zeros((n_obj + n_bg, FEATURE_DIM), dtype=np.float32)
    features[:n_obj, 0] = 1.0
    features[:n_obj, 1:] = goal_flow(p_obj, T_obj, T_goal)
    return {
        "points": points,
        "features": features,
        "normals": obj_normals.take(io, axis=0).astype(np.float32),
    }


def validate_observation(obs: dict[str, np.ndarray], n_obj: int, n_bg: int) -> None:
    """Raise ``ValueError`` naming the tensor when an observation breaks the contract."""
    n = n_obj + n_bg
    want = {"points": (n, 3), "features": (n, FEATURE_DIM), "normals": (n_obj, 3)}
    for name, shape in want.items():
        if name not in obs:
            raise ValueError(f"observation is missing '{name}'")
        a = np.asarray(obs[name])
        if a.shape != shape:
            raise ValueError(f"observation '{name}' has shape {a.shape}, expected {shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"observation '{name}' contains NaN or inf")
