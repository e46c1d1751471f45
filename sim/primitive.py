"""The push primitive (HACMan's poke) and the workspace gate: their one home.

Pure numpy. The simulator, the MuJoCo twin and the real robot all take their waypoints from
``primitive_waypoints`` and refuse plans with ``check_plan``, so a primitive means the same thing in
training and on the arm.

Geometry (fingertip positions, world/base frame, metres; gripper pointing down, fingers closed)::

    w0 = p + 0.04 n          pre-contact (teleported to in training; approached from above on a robot)
    w1 = p + 0.02 n
    w2 = p                   contact
    w3..w5 = w2 + k·0.03·m   three pushes of 3 cm · motion, k = 1, 2, 3
    w6 = w5 + [0, 0, 0.06]   retract straight up

Every waypoint's height is clamped to ≥ floor + 5 mm *before* the workspace check (part of the
primitive's definition: a push with a downward component slides along the floor). After clamping, a
plan with any waypoint outside the workspace box is refused, never clipped.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

PRE_CONTACT_OFFSET_M = 0.04  # start this far out along the surface normal
APPROACH_OFFSET_M = 0.02  # second waypoint along the normal
PUSH_STEP_M = 0.03  # each of the three pushes moves 3 cm × motion component
N_PUSH_STEPS = 3
RETRACT_HEIGHT_M = 0.06  # straight-up retract after the last push
FLOOR_CLEARANCE_M = 0.005  # fingertip never commanded lower than this above the bin floor
N_WAYPOINTS = 3 + N_PUSH_STEPS + 1
PUSH_SEGMENTS = tuple(range(3, 3 + N_PUSH_STEPS))  # waypoint indices reached by pushing moves
#: N, the contact-force stop: a primitive stops when the net contact force on the hand exceeds this.
#: The cell's default ``force_stop_n`` (``robot.cell.Limits``) and the training hand's (``sim.scene``),
#: so that a policy never learns a push that the arm would stop.
FORCE_STOP_N = 30.0


# Bin of HACMan's scene: inner size 0.45 x 0.54 x 0.107 m, floor top at z = 0, centred at x = y = 0.
BIN_INNER_SIZE_M = np.array([0.45, 0.54, 0.107])
BIN_FLOOR_Z = 0.0


class PrimitiveRejected(ValueError):
    """A plan that must not be executed; the message names waypoint, axis and bound."""


@dataclass(frozen=True)
class Workspace:
    """Axis-aligned box (metres) every fingertip waypoint must lie in, and the bin floor height."""

    low: tuple[float, float, float]
    high: tuple[float, float, float]
    floor_z: float = BIN_FLOOR_Z

    def __post_init__(self):
        lo, hi = np.asarray(self.low, float), np.asarray(self.high, float)
        if lo.shape != (3,) or hi.shape != (3,) or not np.all(hi > lo):
            raise ValueError(f"workspace box must have low < high on x, y, z; got {self.low}, {self.high}")
        if not lo[2] <= self.floor_z + FLOOR_CLEARANCE_M:
            raise ValueError("workspace low z must not be above floor + clearance")


#: The simulated cell's workspace: the bin interior shrunk by 1.2 cm at the walls (half the closed
#: fingers' width plus margin) and up to 0.25 m above the floor.
SIM_WORKSPACE = Workspace(
    low=(-0.225 + 0.012, -0.27 + 0.012, BIN_FLOOR_Z),
    high=(0.225 - 0.012, 0.27 - 0.012, BIN_FLOOR_Z + 0.25),
)


def primitive_waypoints(
    point: np.ndarray, normal: np.ndarray, motion: np.ndarray, floor_z: float = BIN_FLOOR_Z
) -> np.ndarray:
    """Fingertip waypoints (..., N_WAYPOINTS, 3) for contact ``point`` (..., 3), unit ``normal`` (..., 3)
    and ``motion`` (..., 3) in [-1, 1] (clipped to that range: it is the policy's squashed output).

    Leading dimensions broadcast, so one call plans a primitive at every point of a cloud."""
    p = np.asarray(point, dtype=np.float64)
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-9)
    m = np.clip(np.asarray(motion, dtype=np.float64), -1.0, 1.0)
    p, n, m = np.broadcast_arrays(p, n, m)
    w = np.empty((*p.shape[:-1], N_WAYPOINTS, 3))
    w[..., 0, :] = p + PRE_CONTACT_OFFSET_M * n
    w[..., 1, :] = p + APPROACH_OFFSET_M * n
    w[..., 2, :] = p
    for k in range(1, N_PUSH_STEPS + 1):
        w[..., 2 + k, :] = p + k * PUSH_STEP_M * m
    w[..., 2] = np.maximum(w[..., 2], floor_z + FLOOR_CLEARANCE_M)
    w[..., -1, :] = w[..., -2, :]
    w[..., -1, 2] += RETRACT_HEIGHT_M
    return w


def plans_inside(waypoints: np.ndarray, workspace: Workspace = SIM_WORKSPACE) -> np.ndarray:
    """Boolean (...) : which plans ``waypoints`` (..., K, 3) ``check_plan`` would accept.

    The vectorised form of the workspace gate, for choosing among candidate plans (the location
    policy's feasible points); executing a plan still goes through ``check_plan``."""
    w = np.asarray(waypoints, dtype=np.float64)
    lo, hi = np.asarray(workspace.low) - 1e-9, np.asarray(workspace.high) + 1e-9
    ok = np.isfinite(w).all(-1) & (w >= lo).all(-1) & (w <= hi).all(-1)  # (..., K)
    return ok.all(-1)


def check_plan(waypoints: np.ndarray, workspace: Workspace = SIM_WORKSPACE) -> None:
    """Raise ``PrimitiveRejected`` unless every waypoint is finite and inside ``workspace``.

    Segments between waypoints are straight lines, so a box containing every waypoint contains every
    segment too.
    """
    w = np.asarray(waypoints, dtype=np.float64)
    if w.ndim != 2 or w.shape[1] != 3:
        raise PrimitiveRejected(f"waypoints must have shape (K, 3), got {w.shape}")
    if not np.all(np.isfinite(w)):
        raise PrimitiveRejected("waypoints contain NaN or inf")
    lo, hi = np.asarray(workspace.low), np.asarray(workspace.high)
    if (w >= lo - 1e-9).all() and (w <= hi + 1e-9).all():  # inside: no need to find which bound fails
        return
    for i, wp in enumerate(w):
        for axis, name in enumerate("xyz"):
            if wp[axis] < lo[axis] - 1e-9:
                raise PrimitiveRejected(
                    f"waypoint {i} {name}={wp[axis]:.3f} m is below the workspace bound {lo[axis]:.3f} m"
                )
            if wp[axis] > hi[axis] + 1e-9:
                raise PrimitiveRejected(
                    f"waypoint {i} {name}={wp[axis]:.3f} m is above the workspace bound {hi[axis]:.3f} m"
                )


#: The hand's collision boxes as (centre, half-size) relative to the fingertip at a start waypoint,
#: metres, gripper pointing down: the closed finger pads and the palm (sim/assets/hand.xml; a test
#: checks the two agree). The palm is 20 cm wide along y.
HAND_BOXES = (
    ((0.0, 0.0, 0.022), (0.012, 0.03, 0.022)),
    ((0.0, 0.0, 0.092), (0.0315, 0.102, 0.046)),
)
_BIN_LOW = (-BIN_INNER_SIZE_M[0] / 2, -BIN_INNER_SIZE_M[1] / 2, BIN_FLOOR_Z)  # inner box of the simulated bin
_BIN_HIGH = (BIN_INNER_SIZE_M[0] / 2, BIN_INNER_SIZE_M[1] / 2, BIN_FLOOR_Z + BIN_INNER_SIZE_M[2])
START_TOLERANCE_M = 0.003  # overlap tolerated at the start pose (the simulator's START_PENETRATION_M)


def hand_hits_cloud(fingertip: np.ndarray, cloud: np.ndarray) -> np.ndarray:
    """Boolean (B, N): whether the hand with its fingertip at ``fingertip`` (B, N, 3) encloses any point
    of the observed ``cloud`` (B, M, 3) deeper than the start tolerance.

    Per-axis float32 comparisons of (B, N, M) arrays: ~20x faster than one (B, N, M, 3) float64
    difference reduced over its last axis (1.6 vs 35 ms for 8 x 128 x 256), which matters because
    this runs at every decision."""
    f = np.asarray(fingertip, dtype=np.float32)
    cloud = np.asarray(cloud, dtype=np.float32)
    hit = np.zeros(f.shape[:2], dtype=bool)
    for centre, half in HAND_BOXES:
        c = f + np.asarray(centre, dtype=np.float32)  # (B, N, 3) box centres
        limit = np.asarray(half, dtype=np.float32) - START_TOLERANCE_M
        inside = np.abs(cloud[:, None, :, 2] - c[:, :, None, 2]) < limit[2]  # (B, N, M)
        for axis in (0, 1):
            inside &= np.abs(cloud[:, None, :, axis] - c[:, :, None, axis]) < limit[axis]
        hit |= inside.any(-1)
    return hit


def within_walls(
    fingertip: np.ndarray,
    bin_low: np.ndarray = _BIN_LOW,
    bin_high: np.ndarray = _BIN_HIGH,
) -> np.ndarray:
    """Boolean (...): whether the hand with its fingertip at ``fingertip`` (..., 3) stays off the bin's
    walls: every hand box below the rim (``bin_high[2]``) lies inside the inner box in x and y."""
    f = np.asarray(fingertip, dtype=np.float64)
    lo_bin, hi_bin = np.asarray(bin_low, float), np.asarray(bin_high, float)
    ok = np.ones(f.shape[:-1], dtype=bool)
    for centre, half in HAND_BOXES:
        c, h = f + centre, np.asarray(half)
        below_rim = c[..., 2] - h[2] < hi_bin[2] - START_TOLERANCE_M
        inside = (
            (c[..., :2] - h[:2] >= lo_bin[:2] - START_TOLERANCE_M)
            & (c[..., :2] + h[:2] <= hi_bin[:2] + START_TOLERANCE_M)
        ).all(-1)
        ok &= inside | ~below_rim
    return ok


def start_clear(
    start: np.ndarray, cloud: np.ndarray, bin_low: np.ndarray = _BIN_LOW, bin_high: np.ndarray = _BIN_HIGH
) -> np.ndarray:
    """Boolean (B, N): a point-cloud approximation of the simulator's start-pose collision test
    (``sim.scene``, which stays the authority): the hand at each ``start`` (B, N, 3) neither encloses
    points of ``cloud`` (B, M, 3) nor overlaps the bin's walls."""
    return within_walls(start, bin_low, bin_high) & ~hand_hits_cloud(start, cloud)


def feasible_points(
    points: np.ndarray,
    normals: np.ndarray,
    motions: np.ndarray,
    cloud: np.ndarray | None = None,
    workspace: Workspace = SIM_WORKSPACE,
    bin_box: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Boolean (B, N_obj): whether the primitive at each object point can run.

    ``points``, ``normals``, ``motions`` (B, N_obj, 3): contact candidates and the motion the policy
    proposes at each. A plan must pass the workspace gate, keep the hand off the bin's walls from the
    start through the last push (``bin_box`` = (low, high), default the simulated bin) and, given
    the observed ``cloud`` (B, M, 3), start with the hand clear of it. The location policy chooses
    among these points: a refused push wastes a primitive and, for a deterministic policy, repeats
    until the episode times out; a push that presses the 20 cm palm on the rim is tolerated by the
    force-limited training hand but stops a real arm (contact-force stop or reflex)."""
    waypoints = primitive_waypoints(points, normals, motions, workspace.floor_z)
    ok = plans_inside(waypoints, workspace)
    ok &= within_walls(waypoints[..., : N_WAYPOINTS - 1, :], *(bin_box or ())).all(-1)
    if cloud is not None:
        ok &= ~hand_hits_cloud(waypoints[..., 0, :], cloud)
    return ok


#: The feasibility mask of one batch of observations, as a function of the motion the policy proposes
#: at each object point: ``motions (B, N_obj, 3) in [-1, 1]`` → ``bool (B, N_obj)``.
FeasibilityMask = Callable[[np.ndarray], np.ndarray]


def feasibility_mask(
    points: np.ndarray,
    normals: np.ndarray,
    workspace: Workspace = SIM_WORKSPACE,
    bin_box: tuple[np.ndarray, np.ndarray] | None = None,
) -> FeasibilityMask:
    """The mask the location policy chooses under, made where the observation is made.

    ``points (B, N, 3)``: the observed clouds, object points first (metres); ``normals (B, N_obj, 3)``:
    the object points' unit normals. Whether a push can run depends on the motion proposed at the
    point, which only the policy knows, so the mask is handed to the policy (``HybridAgent.act``,
    ``OnnxPolicy.decide``) as a function of those motions: :func:`feasible_points` against the whole
    cloud, with every point allowed in a row where none is feasible (the gate then refuses the plan
    with its reason)."""
    points = np.asarray(points)
    normals = np.asarray(normals)
    n_obj = normals.shape[1]

    def mask(motions: np.ndarray) -> np.ndarray:
        feasible = feasible_points(points[:, :n_obj], normals, motions, points, workspace, bin_box)
        return feasible | ~feasible.any(-1, keepdims=True)

    return mask
