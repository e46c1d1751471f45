"""Goal clouds and registration: the current object cloud → the goal cloud, giving the goal flow.

Training defines ``goal_flow = T_goal · T_obj⁻¹ · p − p``: the rigid transform that carries the object
from where it is to where it should be, applied to each observed point. On a robot neither pose is
known; :func:`register` estimates that transform ``T`` (4, 4) directly, as the one that maps the
current object cloud onto the goal cloud (``goal.npz``, recorded by ``hydo deploy capture-goal``):

1. global initialisation: the current cloud's centroid moved onto the goal's, under each of a fixed
   set of candidate rotations (yaw every 10° for planar goals; 24 axis-aligned orientations × yaw
   every 30° for 6d goals), scored by the trimmed mean nearest-neighbour distance of a subsample
   (one vectorised ``cKDTree`` query for all candidates). The current orientation itself (no turn)
   is always an ICP start besides the best-scoring ones: an object symmetric about an axis (a bowl,
   a cylinder) scores alike under every turn about it, and only the start without one finds the
   pose that needs the least motion;
2. trimmed point-to-point ICP (Kabsch) from the best few, keeping the closest 80% of
   correspondences (the two clouds are partial views of different sides);
3. residuals: RMS of inlier distances (< 1 cm) and the inlier fraction. The inlier fraction counts
   only the current points the goal's cameras would see with the object at the goal (``cameras``:
   :func:`goal_visible`): a goal that puts another face up shows less of what is visible now, and a
   point that moves to the underside or the far side cannot have a goal point near it however good
   the fit. Their share of the current points is the ``overlap``. A poor registration (RMS, inliers,
   or too little overlap to judge) is refused (``RegistrationError`` with its residuals); there is no
   approximate fallback;
4. ambiguity: the ICP starts are distinct rotations (at least ``DISTINCT_START_DEG`` apart); every
   solution that fits about as well as the best (trimmed RMS within ``AMBIGUOUS_RMS`` × best +
   ``AMBIGUOUS_SLACK_M``) is a candidate. The registration is the nearest (least motion) of the
   candidates that agree with the goal cloud about as closely as the best (the two-way share of
   points within ``AGREE_M`` of the other cloud, within ``AGREE_TOL`` of the best: a bottle turned
   end over end fits within the RMS band but not this). The candidates moving the object
   differently from it (mean over the points by more than ``AMBIGUOUS_DISTINCT_M``) are kept as
   alternatives: a symmetric or nearly symmetric object (a box turned 180°, a mug whose handle is
   hidden) matches its goal cloud in more than one pose, and the clouds alone cannot say which one
   the goal meant. Goals are reached up to the object's symmetry (``sim.contract``), so that only
   matters when the views differ: :meth:`Registration.verdict` calls ``ambiguous`` a registration
   whose alternatives fall on the other side of the threshold, when the goal cloud shows surface
   the current cloud lacks (``goal_coverage`` under ``COVERAGE_MIN``).

The measured distance to the goal is ``mean ‖T p − p‖`` over the current object points: the reward's
quantity, so success is the same 3 cm threshold as in training. Symmetric objects fit their goal
cloud in several poses: the flow points to the nearest of them, the others are reported as
alternatives (step 4).
"""

from __future__ import annotations

import functools
import itertools
import json
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from robot.errors import RegistrationError
from sim.contract import transform_points
from sim.depth import seen_from_cameras

INLIER_M = 0.01  # a correspondence closer than this is an inlier
TRIM = 0.8  # ICP fits the closest 80% of correspondences
ICP_ITERS = 30
COARSE_POINTS = 96  # source points scored per candidate rotation
MAX_SOURCE_POINTS = 400
MAX_TARGET_POINTS = 3000
REFINE_CANDIDATES = 6  # ICP starts: the best-scoring coarse rotations ...
WIDE_ROTATIONS = 4000  # search="wide": this many uniformly random rotations (6d; planar: yaw every 2°) ...
WIDE_REFINE_CANDIDATES = 16  # ... and this many ICP starts
DISTINCT_START_DEG = 25.0  # ... at least this far apart (so that distinct solutions are found)
AMBIGUOUS_RMS = 1.25
AMBIGUOUS_SLACK_M = 0.0005
AMBIGUOUS_DISTINCT_M = 0.015
AGREE_M = 0.005  # two-way agreement of a candidate fit: points with a counterpart this close ...
AGREE_TOL = 0.03  # ... and the candidates kept: within this of the best fit's agreement
COVERAGE_MIN = 0.92  # of the goal cloud within INLIER_M of the registered current cloud: the views agree
# A success is claimed only where the two views match as an object at its goal makes them match:
# this much of the goal cloud covered and of the current points the goal shows inliers. Of the
# twin's registrations under 2.5 cm, coverage is under 0.95 in 5 of 196 truly within 3 cm and 18 of
# 23 not; inliers under 0.9 in 1 of 196 and 6 of 23 (`python bench/verdict.py` on three ladder
# sessions' twin logs, docs/results.md)
SUCCESS_COVERAGE_MIN = 0.95
SUCCESS_INLIERS_MIN = 0.9
COVERAGE_POINTS = 500
GOAL_FORMAT = "hydo-goal/1"
GOAL_KINDS = ("captured", "offset")  # Goal.kind: the object placed at the goal | the start cloud moved


@dataclass
class Registration:
    """``T`` maps current object points onto the goal cloud; residuals say how well."""

    T: np.ndarray  # (4, 4)
    rmse: float  # m, RMS of inlier correspondence distances
    inlier_fraction: (
        float  # of the current points the goal would show (overlap): a goal point within INLIER_M
    )
    distance: float  # m, mean ‖T p − p‖ over the current object points (the reward's quantity)
    seconds: float
    # distances (m) of other solutions that fit about as well but move the object differently
    alternatives: tuple[float, ...] = ()
    # fraction of the goal cloud within INLIER_M of the registered current cloud: low when the goal
    # view shows surface the current view does not (a mug's handle hidden now, seen at the goal)
    goal_coverage: float = 1.0
    # fraction of the current points that the goal's cameras would see at the goal (1 without cameras)
    overlap: float = 1.0
    # the alternatives are never the object's symmetry (registration to its model folds that into the
    # flow, robot.model_registration): one on the other side of the threshold is always ambiguous
    folded: bool = False

    @property
    def ambiguous(self) -> bool:
        return bool(self.alternatives)

    def verdict(self, threshold: float, margin: float = 0.0) -> str:
        """``failure`` when the registration is ``threshold`` or further and either no other equally
        good fit is nearer or the goal cloud is covered (``COVERAGE_MIN``: both views show the same
        surface, so the fits that disagree are the object's own symmetry, and goals are reached up
        to symmetry, ``sim.contract``). Nearer: ``ambiguous`` when the goal cloud is not covered and
        another equally good fit is further (the current view lacks surface the goal view shows,
        and the fits disagree on whether it is at the goal); ``uncertain`` within ``margin`` under
        the threshold (the registration's own distance error, checked first), or when the views do
        not match as closely as an object at its goal makes them (``SUCCESS_COVERAGE_MIN``,
        ``SUCCESS_INLIERS_MIN``: a mug whose handle the fit put elsewhere); else ``success``. With
        ``folded`` alternatives, coverage cannot make them the object's symmetry: they count always."""
        covered = self.goal_coverage >= COVERAGE_MIN and not self.folded
        if self.distance >= threshold:
            return "failure" if covered or all(a >= threshold for a in self.alternatives) else "ambiguous"
        if self.distance >= threshold - margin:
            return "uncertain"
        if not covered and any(a >= threshold for a in self.alternatives):
            return "ambiguous"
        if self.goal_coverage < SUCCESS_COVERAGE_MIN or self.inlier_fraction < SUCCESS_INLIERS_MIN:
            return "uncertain"
        return "success"

    def to_json(self) -> dict:
        return {
            "T": np.round(self.T, 6).tolist(),
            "rmse_m": round(self.rmse, 6),
            "inlier_fraction": round(self.inlier_fraction, 4),
            "distance_m": round(self.distance, 6),
            "alternative_distances_m": [round(a, 6) for a in self.alternatives],
            "goal_coverage": round(self.goal_coverage, 4),
            "overlap": round(self.overlap, 4),
            "seconds": round(self.seconds, 4),
            "folded": self.folded,
        }


def _rot_z(a: np.ndarray) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    R = np.zeros((len(a), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 1, 0], R[:, 1, 1], R[:, 2, 2] = c, -s, s, c, 1.0
    return R


@functools.cache
def _cube_group() -> np.ndarray:
    """The 24 rotations mapping the coordinate axes onto themselves (3, 3) each."""
    out = []
    for perm in itertools.permutations(range(3)):
        for signs in itertools.product((1.0, -1.0), repeat=3):
            R = np.zeros((3, 3))
            R[range(3), perm] = signs
            if np.linalg.det(R) > 0:
                out.append(R)
    return np.array(out)


@functools.cache
def candidate_rotations(mode: str, search: str = "fast") -> np.ndarray:
    """Initial rotations (C, 3, 3). ``fast``: yaw every 10° (planar) or 24 orientations × yaw every 30°
    (6d). ``wide``: yaw every 2° (planar) or ``WIDE_ROTATIONS`` uniformly random rotations (6d, fixed
    seed): a goal with another face up is often no axis-aligned turn of the current view away."""
    if mode == "planar":
        return _rot_z(np.deg2rad(np.arange(0, 360, 10 if search == "fast" else 2)))
    if search == "wide":
        return Rotation.random(WIDE_ROTATIONS, random_state=0).as_matrix()
    yaw = _rot_z(np.deg2rad(np.arange(0, 360, 30)))
    return np.einsum("yij,gjk->ygik", yaw, _cube_group()).reshape(-1, 3, 3)


def kabsch(a: np.ndarray, b: np.ndarray, planar: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R (3, 3) and translation t (3,) minimising Σ‖R a + t − b‖² (yaw only if ``planar``)."""
    ca, cb = a.mean(0), b.mean(0)
    A, B = a - ca, b - cb
    if planar:
        ang = np.arctan2(
            np.sum(A[:, 0] * B[:, 1] - A[:, 1] * B[:, 0]), np.sum(A[:, 0] * B[:, 0] + A[:, 1] * B[:, 1])
        )
        R = _rot_z(np.array([ang]))[0]
    else:
        U, _, Vt = np.linalg.svd(A.T @ B)
        D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
        R = Vt.T @ D @ U.T
    return R, cb - R @ ca


def _icp(src: np.ndarray, tgt: np.ndarray, tree: cKDTree, T: np.ndarray) -> tuple[np.ndarray, float]:
    """Trimmed point-to-point ICP from ``T``; returns ``(T, trimmed RMS)``."""
    T = T.copy()
    rms = np.inf
    for _ in range(ICP_ITERS):
        x = transform_points(T, src)
        d, j = tree.query(x)
        keep = d <= np.quantile(d, TRIM)
        R, t = kabsch(x[keep], tgt[j[keep]])
        step = np.eye(4)
        step[:3, :3], step[:3, 3] = R, t
        T = step @ T
        new_rms = float(np.sqrt(np.mean(d[keep] ** 2)))
        if abs(rms - new_rms) < 1e-6 and np.linalg.norm(t) < 1e-5:
            rms = new_rms
            break
        rms = new_rms
    return T, rms


def _subsample(p: np.ndarray, n: int, rng: np.random.Generator) -> np.ndarray:
    return p if len(p) <= n else p[rng.choice(len(p), n, replace=False)]


def icp_solutions(
    src: np.ndarray,
    tgt: np.ndarray,
    tree: cKDTree,
    mode: str,
    search: str,
    rng: np.random.Generator,
    starts: Sequence[np.ndarray] = (),
) -> list[tuple[float, np.ndarray]]:
    """Trimmed ICP of ``src (M, 3)`` onto ``tgt (G, 3)`` (``tree``: its KD-tree) from distinct starts:
    ``(trimmed RMS, T (4, 4))`` each, in start order. The starts: ``starts`` (full transforms: a
    pose known from before), the current orientation (no turn), then the best-scoring coarse
    rotations (:func:`candidate_rotations`, centroids aligned), at least ``DISTINCT_START_DEG`` apart."""
    cs, ct = src.mean(0), tgt.mean(0)
    coarse = _subsample(src, COARSE_POINTS, rng) - cs  # (m, 3)
    Rs = candidate_rotations(mode, search)  # (C, 3, 3)
    x = np.einsum("cij,mj->cmi", Rs, coarse) + ct  # (C, m, 3)
    d, _ = tree.query(x.reshape(-1, 3))
    d = np.sort(d.reshape(len(Rs), -1), axis=1)[:, : int(TRIM * coarse.shape[0])]
    n = REFINE_CANDIDATES if search == "fast" else WIDE_REFINE_CANDIDATES
    no_turn = np.eye(3)
    T0s = [np.asarray(T, float) for T in starts]
    for R0 in [no_turn, *Rs[_distinct_starts(Rs, d.mean(1), n, taken=(no_turn,))]]:
        T0 = np.eye(4)
        T0[:3, :3] = R0
        T0[:3, 3] = ct - R0 @ cs
        T0s.append(T0)
    return [(rms, T) for T, rms in (_icp(src, tgt, tree, T0) for T0 in T0s)]


def register(
    source: np.ndarray,
    target: np.ndarray,
    mode: str = "6d",
    seed: int = 0,
    cameras: Sequence = (),
    search: str = "fast",
) -> Registration:
    """Register the current object cloud ``source (M, 3)`` to the goal cloud ``target (G, 3)``, both
    in the base frame (m). ``cameras``: the cell's ``CameraSpec``s that captured the goal; with them
    the inlier fraction counts only the points the goal can show (:func:`goal_visible`). ``search``:
    ``fast`` (~0.1 s) or ``wide`` (more initial rotations and ICP starts, ~0.7 s), which
    :func:`register_checked` runs when the fast one fails its checks."""
    t0 = time.perf_counter()
    source = np.asarray(source, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    if len(source) < 10 or len(target) < 10:
        raise RegistrationError(
            f"registration needs at least 10 points each (have {len(source)} and {len(target)})"
        )
    rng = np.random.default_rng(seed)
    src = _subsample(source, MAX_SOURCE_POINTS, rng)
    tgt = _subsample(target, MAX_TARGET_POINTS, rng)
    tree = cKDTree(tgt)
    solutions = []  # (trimmed RMS, T) of ICP from each distinct start
    for rms, T in icp_solutions(src, tgt, tree, mode, search, rng):
        if len(cameras):
            # refit on the points the goal can show: the others have no counterpart in the goal cloud
            # and pull a fit that must match views of different faces (a flip) towards them. The
            # solution keeps its ranking by the whole cloud's fit, so hiding points cannot win it
            seen = goal_visible(transform_points(T, src), tgt, cameras)
            if seen.sum() >= 10:
                T, _ = _icp(src[seen], tgt, tree, T)
        solutions.append((rms, T))
    solutions.sort(key=lambda s: s[0])
    band = AMBIGUOUS_RMS * solutions[0][0] + AMBIGUOUS_SLACK_M
    # Every solution that fits about as well as the best, as moved source points, nearest first: of
    # poses the clouds cannot tell apart, the flow points to the one needing the least motion (for a
    # planar goal, which keeps the object's yaw, that is the goal itself for a symmetric object).
    fits = [(transform_points(T, source), T) for rms, T in solutions if rms <= band]
    probe = _subsample(tgt, COVERAGE_POINTS, rng)
    fits.sort(key=lambda f: np.linalg.norm(f[0] - source, axis=1).mean())
    agreeing = fits
    if len(fits) > 1:
        # The trimmed RMS cannot tell a nearly symmetric object's wrong fit (a bottle turned end over
        # end: its ends differ by a few mm) from the right one, and the wrong one often moves less.
        # Close agreement both ways can: the registration is the nearest of the fits within
        # AGREE_TOL of the best agreement. The others stay alternatives: with partial views a fit
        # that has not quite settled loses agreement too, so they are not ruled out (verdict).
        agree = [_agreement(m, tree, probe, target, cameras) for m, _ in fits]
        agreeing = [f for f, a in zip(fits, agree, strict=True) if a >= max(agree) - AGREE_TOL]
    moved, best_T = agreeing[0]
    d_all, _ = tree.query(moved)
    inl = d_all < INLIER_M
    rmse = float(np.sqrt(np.mean(d_all[inl] ** 2))) if inl.any() else np.inf
    seen = goal_visible(moved, target, cameras) if len(cameras) else np.ones(len(moved), bool)
    inlier_fraction = float(inl[seen].mean()) if seen.any() else 0.0
    distance = float(np.linalg.norm(moved - source, axis=1).mean())
    alternatives: list[np.ndarray] = []  # the distinct other ones
    for other, _ in fits:
        if all(
            np.linalg.norm(other - m, axis=1).mean() > AMBIGUOUS_DISTINCT_M for m in (moved, *alternatives)
        ):
            alternatives.append(other)
    alt = tuple(float(np.linalg.norm(m - source, axis=1).mean()) for m in alternatives)
    coverage = float((cKDTree(moved).query(probe)[0] < INLIER_M).mean())
    return Registration(
        best_T, rmse, inlier_fraction, distance, time.perf_counter() - t0, alt, coverage, float(seen.mean())
    )


def _agreement(
    moved: np.ndarray, tree: cKDTree, probe: np.ndarray, target: np.ndarray, cameras: Sequence
) -> float:
    """How closely a fit's moved current cloud ``moved (M, 3)`` and the goal cloud agree, both ways:
    the mean of the share of the moved points the goal can show (:func:`goal_visible`) that have a
    goal point (``tree``) within ``AGREE_M``, and the share of goal points ``probe (P, 3)`` with a
    moved point within ``AGREE_M``. Equal for the poses of a symmetry; lower for a near miss."""
    seen = goal_visible(moved, target, cameras) if len(cameras) else np.ones(len(moved), bool)
    near = tree.query(moved[seen])[0] < AGREE_M if seen.any() else np.zeros(1, bool)
    covered = cKDTree(moved).query(probe)[0] < AGREE_M
    return 0.5 * (float(near.mean()) + float(covered.mean()))


def goal_visible(points: np.ndarray, goal: np.ndarray, cameras: Sequence) -> np.ndarray:
    """Which of ``points (M, 3)`` (the current cloud moved to the goal by the registration, base frame)
    the goal's ``cameras`` (``robot.cell`` camera specs) would see: (M,) bool.

    ``sim.depth.seen_from_cameras`` with the goal cloud ``goal (G, 3)`` as the surface in front: a
    moved point more than ``VISIBILITY_DEPTH_M`` behind it is the object's own far side or underside.
    A point where the goal shows nothing (outside its silhouette) counts as seen: a fit that puts
    points there is wrong, and they count against it as outliers."""
    views = [(cam.K, cam.T_base_camera, (cam.height, cam.width)) for cam in cameras]
    return seen_from_cameras(points, goal, views)


def _distinct_starts(
    Rs: np.ndarray, score: np.ndarray, n: int = REFINE_CANDIDATES, taken: Sequence[np.ndarray] = ()
) -> list[int]:
    """Up to ``n`` indices of the best-scoring (lowest) rotations ``Rs (C, 3, 3)``, each at least
    ``DISTINCT_START_DEG`` from those already picked and from the rotations ``taken`` (3, 3) each."""
    cos_min = np.cos(np.deg2rad(DISTINCT_START_DEG))
    picked: list[int] = []
    for c in np.argsort(score):
        # rotation angle between R_c and R_t: cos θ = (tr(R_c R_tᵀ) − 1) / 2
        if all((np.trace(Rs[c] @ R.T) - 1) / 2 < cos_min for R in (*taken, *Rs[picked])):
            picked.append(int(c))
            if len(picked) == n:
                break
    return picked


def adds_error(T_est: np.ndarray, T_true: np.ndarray, points: np.ndarray) -> float:
    """ADD-S (m): mean distance from each ``T_est·p`` to the nearest ``T_true·q`` over ``points``.

    The symmetric-object pose error (a cube turned 90° registers perfectly and scores ~0).
    """
    est, true = transform_points(T_est, points), transform_points(T_true, points)
    return float(cKDTree(true).query(est)[0].mean())


def registration_problem(reg: Registration, max_rmse: float, min_inliers: float, min_overlap: float = 0.0):
    """Why ``reg`` is too poor to act on (one line), or None."""
    if reg.overlap < min_overlap:
        return (
            f"registration to the goal failed: only {reg.overlap:.0%} of the object's visible points "
            f"would be visible at the goal (min {min_overlap:.0%}): too little shared surface to check the "
            "fit; record the goal from cameras that see more of the object, or reach it in two goals"
        )
    if not np.all(np.isfinite(reg.T)) or reg.rmse > max_rmse or reg.inlier_fraction < min_inliers:
        return (
            f"registration to the goal failed: inlier RMS {reg.rmse * 1000:.1f} mm (max {max_rmse * 1000:.1f}), "
            f"inliers {reg.inlier_fraction:.0%} of the points the goal shows (min {min_inliers:.0%}); "
            "wrong object, or too noisy: refusing to act"
        )
    return None


def check_registration(
    reg: Registration, max_rmse: float, min_inliers: float, min_overlap: float = 0.0
) -> None:
    """Refuse to act on a poor registration, with its residuals (no approximate fallback)."""
    problem = registration_problem(reg, max_rmse, min_inliers, min_overlap)
    if problem is not None:
        raise RegistrationError(problem)


def register_checked(
    source: np.ndarray, target: np.ndarray, mode: str, seed: int, cameras: Sequence, limits
) -> tuple[Registration, bool]:
    """:func:`register`, and when that fails the cell's checks (``limits``: the cell's ``Perception``)
    the ``wide`` search, kept if it passes or fits better. Returns ``(registration, widened)``; the
    caller still runs :func:`check_registration` on it. The fast search misses the right basin about
    one time in twenty on goals with another face up (a mug's handle turned over, a box's faces of
    nearly equal size); a refusal ends the episode, so it is worth 0.7 s to look again."""
    args = (limits.registration_max_rmse, limits.registration_min_inliers, limits.registration_min_overlap)
    reg = register(source, target, mode, seed, cameras)
    if registration_problem(reg, *args) is None:
        return reg, False
    wide = register(source, target, mode, seed, cameras, search="wide")
    wide.seconds += reg.seconds
    if registration_problem(wide, *args) is None or (wide.inlier_fraction, -wide.rmse) > (
        reg.inlier_fraction,
        -reg.rmse,
    ):
        return wide, True
    reg.seconds = wide.seconds
    return reg, True


# --- goals --------------------------------------------------------------------------------------------


@dataclass
class Goal:
    """A goal cloud (base frame) and how it was made."""

    points: np.ndarray  # (G, 3) float32, object points at the goal pose, robot base frame
    kind: str  # "captured" (the object placed at the goal) | "offset" (the start cloud moved)
    offset: tuple[float, float, float] | None = None  # (dx m, dy m, yaw deg) for "offset" goals
    created_at: float = 0.0

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        meta = {
            "format": GOAL_FORMAT,
            "kind": self.kind,
            "offset": self.offset,
            "created_at": self.created_at,
        }
        tmp = path.with_name(f".{path.name}.tmp.npz")
        np.savez_compressed(tmp, points=self.points.astype(np.float32), meta=np.array(json.dumps(meta)))
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path) -> Goal:
        """Read a ``capture-goal`` file; anything but one (missing, zero bytes, truncated, not an .npz,
        wrong keys, types, shapes or enum values) is one ``RegistrationError`` line naming the file."""
        from robot.perception import read_meta, read_npz

        path = Path(path)
        if not path.is_file():
            raise RegistrationError(
                f"goal {path} does not exist: record one with `hydo deploy capture-goal --out {path}`"
            )
        again = "record it again (`hydo deploy capture-goal`)"
        arrays = read_npz(path, "goal", RegistrationError, again)
        meta = read_meta(arrays, path, "goal", RegistrationError, again)
        if meta.get("format") != GOAL_FORMAT:
            raise RegistrationError(
                f"goal {path}: format {meta.get('format')!r}, this hydo reads {GOAL_FORMAT!r}"
            )
        points = arrays.get("points")
        if (
            points is None
            or points.dtype.kind not in "fiu"
            or points.ndim != 2
            or points.shape[1] != 3
            or len(points) < 10
            or not np.all(np.isfinite(points))
        ):
            got = "none" if points is None else f"{points.dtype} of shape {points.shape}"
            raise RegistrationError(f"goal {path}: `points` must be at least 10 finite 3D points, got {got}")
        kind, off, created = meta.get("kind", "captured"), meta.get("offset"), meta.get("created_at", 0)
        if kind not in GOAL_KINDS:
            raise RegistrationError(
                f"goal {path}: `meta.kind` must be one of {list(GOAL_KINDS)}, got {kind!r}"
            )
        if off is not None and not (
            isinstance(off, list)
            and len(off) == 3
            and all(isinstance(v, int | float) and not isinstance(v, bool) for v in off)
        ):
            raise RegistrationError(
                f"goal {path}: `meta.offset` must be null or [dx, dy, yaw_deg], got {off!r}"
            )
        if isinstance(created, bool) or not isinstance(created, int | float):
            raise RegistrationError(f"goal {path}: `meta.created_at` must be a number, got {created!r}")
        return cls(points.astype(np.float32), kind, tuple(off) if off else None, float(created))


def offset_transform(points: np.ndarray, dx: float, dy: float, yaw_deg: float = 0.0) -> np.ndarray:
    """(4, 4): rotate ``yaw_deg`` about the vertical through the cloud's centroid, then shift (dx, dy)."""
    c = np.asarray(points, dtype=np.float64).mean(0)
    R = _rot_z(np.array([np.deg2rad(yaw_deg)]))[0]
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = c - R @ c + np.array([dx, dy, 0.0])
    return T


def goal_from_offset(points: np.ndarray, dx: float, dy: float, yaw_deg: float = 0.0) -> Goal:
    """A planar goal: the current object cloud moved by ``(dx, dy)`` metres and turned ``yaw_deg``."""
    T = offset_transform(points, dx, dy, yaw_deg)
    return Goal(
        transform_points(T, np.asarray(points, np.float64)).astype(np.float32),
        "offset",
        (dx, dy, yaw_deg),
        time.time(),
    )


def parse_offset(text: str) -> tuple[float, float, float]:
    """``"DX,DY[,YAW_DEG]"`` (metres, metres, degrees) → a tuple; raises ``ValueError``."""
    parts = [p.strip() for p in text.split(",")]
    if len(parts) not in (2, 3):
        raise ValueError(f"a goal offset is DX,DY[,YAW_DEG] (metres, metres, degrees). Got {text!r}.")
    vals = [float(p) for p in parts] + ([0.0] if len(parts) == 2 else [])
    if not all(np.isfinite(vals)):
        raise ValueError(f"a goal offset must be finite. Got {text!r}.")
    if np.hypot(vals[0], vals[1]) > 0.5:
        raise ValueError(f"a goal offset of {np.hypot(vals[0], vals[1]):.2f} m leaves any bin. Got {text!r}.")
    return vals[0], vals[1], vals[2]
