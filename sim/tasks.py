"""Behaviour-diversity tasks (paper §V-C): fixed-start variants of the bin task with behaviour descriptors.

HyDo measures how diverse a policy is by its *behaviour entropy* (Jia et al. 2024)::

    H(π) = −Σ_{b ∈ B} π(b) log_|B| π(b)          (0: one behaviour, 1: all |B| equally often)

where ``π(b)`` is the fraction of evaluation episodes, all started from the same fixed pose, whose
trajectory shows behaviour ``b``. A task here is the bin env (``sim.env.BinEnv(task=...)``) with the
6 cm ``cube``, a fixed start pose (``task_start="fixed"``, evaluation) or a random one in a start region
(``task_start="random"``, training, "to enhance diversity"), a goal, static obstacles (boxes welded
to the world: they collide and enter the background cloud like clutter), and a descriptor that maps an
episode's trajectory of :class:`TaskStep` to a behaviour id in ``range(n_behaviours)`` or ``None``.

Success, reward and observations stay the contract's (``sim.contract``): the task only chooses the
goal pose, so ``success`` means mean goal flow < 3 cm.

``push-line`` (|B| = 24)
    The cube starts at (0, −0.08) m, yaw 0, and must be pushed across the line y = 0 (its centre
    beyond the line). The goal follows the cube: its current pose moved in +y to 3 cm beyond the line
    (unchanged once there), so the goal flow is ``max(0, 0.03 − y)`` in +y and contract success is
    exactly "centre across the line". Training starts: x ∈ [−0.12, 0.12], y ∈ [−0.16, −0.04], any yaw.

    Behaviour = the *first executed* (not refused) primitive of the episode, from the fixed start:
    ``id = 6 · face + sector``.

    * ``face`` ∈ {0: +x, 1: +y, 2: −x, 3: −y}: the cube side face the contact point lies on, in the
      cube's frame (the largest of ``d_x, d_y, −d_x, −d_y`` for ``d`` the contact point relative to the
      cube centre; a contact on the top face counts for its nearest side face).
    * ``sector`` ∈ 0..5: the angle φ of the horizontal motion measured from that face's inward normal
      (counter-clockwise about +z) in six 60° sectors centred on it: sector ``k`` holds
      φ ∈ [60°k − 30°, 60°k + 30°) (mod 360°). 0: straight into the face, 1 / 5: diagonally to the
      left / right, 2 / 4: sideways and away, 3: straight away (no push). No horizontal motion counts
      as φ = 0 (sector 0). A straight push is in the middle of a sector, never on a border.

    An episode whose primitives were all refused has no behaviour (``None``).

``push-align`` (|B| = 2)
    The cube starts at (−0.10, 0) m, yaw 0, and must reach (0.10, 0) m turned by 45° (yaw π/4). A
    white 4 × 8 × 6 cm box at the bin's centre blocks the straight path (as tall as the cube, so the
    cube cannot tip onto it; the palm, 4.6 cm above the fingertip and 20 cm wide in y, clears it when
    the fingertip pushes at least 1.4 cm above the floor). Training starts: x ∈ [−0.13, −0.08],
    y ∈ [−0.08, 0.08], any yaw.

    Behaviour = the side on which the cube's centre passes the obstacle: ``0`` (upper, y > 0) or ``1``
    (lower, y ≤ 0), read at the first time the centre crosses the obstacle's centre line x = 0
    (linear interpolation between the poses before and after the crossing primitive). An episode whose
    cube never crosses x = 0 has no behaviour (``None``).

Pure numpy; no MuJoCo, no torch.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from sim.contract import SUCCESS_THRESHOLD_M, pose_matrix

CUBE_HALF_M = 0.03  # the tasks push the built-in 6 cm ``cube``; its origin is its centre
OBSTACLE_RGBA = (0.95, 0.95, 0.95, 1.0)  # the paper's white obstacles
OBSTACLE_SAMPLE_M = 0.005  # grid spacing of an obstacle's background points


def yaw_quat(yaw: float) -> np.ndarray:
    """Unit quaternion (4,) wxyz of a rotation by ``yaw`` rad about +z."""
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


@dataclass(frozen=True)
class Obstacle:
    """A static box welded to the world: collides with the object and the hand (geom group 0, so the
    depth cameras see it) and its visible faces enter the mesh observer's background cloud."""

    centre: tuple[float, float, float]  # metres, world frame
    half_size: tuple[float, float, float]  # metres, axis-aligned

    def surface_points(self) -> np.ndarray:
        """Grid points (L, 3) float32 on the top and four side faces (the bottom rests on the floor)."""
        return _box_surface(tuple(self.centre), tuple(self.half_size))


@functools.cache
def _box_surface(centre: tuple[float, ...], half_size: tuple[float, ...]) -> np.ndarray:
    """Cached (the mesh observer asks at every step); read-only (L, 3) float32."""
    c, h = np.asarray(centre), np.asarray(half_size)
    axes = [np.linspace(-h[i], h[i], max(2, round(2 * h[i] / OBSTACLE_SAMPLE_M) + 1)) for i in range(3)]
    faces = []
    for i in range(3):  # the faces normal to axis i: at +h and -h for x and y, only the top for z
        j, k = [a for a in range(3) if a != i]
        gj, gk = np.meshgrid(axes[j], axes[k], indexing="ij")
        for sign in (1.0, -1.0) if i < 2 else (1.0,):
            p = np.empty((gj.size, 3))
            p[:, i], p[:, j], p[:, k] = sign * h[i], gj.ravel(), gk.ravel()
            faces.append(p)
    out = (np.concatenate(faces) + c).astype(np.float32)
    out.flags.writeable = False
    return out


@dataclass(frozen=True)
class TaskStep:
    """One primitive of an episode as a behaviour descriptor sees it (world frame, metres)."""

    contact_point: np.ndarray  # (3,) the chosen object point
    motion: np.ndarray  # (3,) the motion parameter in [-1, 1]
    executed: bool  # False: the primitive was refused and the scene did not change
    pose_before: np.ndarray  # (7,) object position (3,) + quaternion wxyz (4,) before the primitive
    pose_after: np.ndarray  # (7,) after it (and after the object settled)


@dataclass(frozen=True)
class Task:
    """A behaviour-diversity task variant of the bin env (see the module docstring)."""

    name: str
    summary: str
    n_behaviours: int  # |B|
    start: tuple[float, float, float]  # fixed start: x, y (m), yaw (rad) of the cube on the floor
    start_region: tuple[tuple[float, float], tuple[float, float]]  # training: x and y ranges (m)
    goal: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]  # (pos, quat) -> goal pose
    goal_follows_object: bool  # True: the goal is recomputed from the object's pose after every step
    behaviour: Callable[[Sequence[TaskStep]], int | None]
    obstacles: tuple[Obstacle, ...] = ()
    object: str = "cube"
    behaviour_names: tuple[str, ...] = field(default=())

    def start_pose(self, rng: np.random.Generator | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(pos (3,), quat (4,) wxyz)``: the fixed start, or (given ``rng``) a random training start."""
        if rng is None:
            x, y, yaw = self.start
        else:
            (x0, x1), (y0, y1) = self.start_region
            x, y, yaw = rng.uniform(x0, x1), rng.uniform(y0, y1), rng.uniform(-np.pi, np.pi)
        return np.array([x, y, CUBE_HALF_M]), yaw_quat(yaw)


# --- push-line -----------------------------------------------------------------------------------
LINE_Y_M = 0.0  # the line the cube's centre must cross (world y, metres)
N_FACES, N_SECTORS = 4, 6
FACE_NAMES = ("+x", "+y", "-x", "-y")


def _push_line_goal(pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The object's pose moved in +y to 3 cm beyond the line: flow < 3 cm ⟺ centre across the line."""
    goal = np.array(pos, dtype=np.float64)
    goal[1] = max(goal[1], LINE_Y_M + SUCCESS_THRESHOLD_M)
    return goal, np.asarray(quat, dtype=np.float64)


def push_face_and_sector(step: TaskStep) -> tuple[int, int]:
    """``(face, sector)`` of one primitive on an upright cube (definitions in the module docstring)."""
    T = pose_matrix(step.pose_before[:3], step.pose_before[3:7])
    R = T[:3, :3]
    d = R.T @ (np.asarray(step.contact_point, dtype=np.float64) - T[:3, 3])  # cube frame
    face = int(np.argmax([d[0], d[1], -d[0], -d[1]]))
    outward = R @ np.array([(1, 0, 0), (0, 1, 0), (-1, 0, 0), (0, -1, 0)][face], dtype=np.float64)
    inward = -outward[:2] / max(np.linalg.norm(outward[:2]), 1e-12)
    m = np.asarray(step.motion, dtype=np.float64)[:2]
    if np.linalg.norm(m) < 1e-9:
        phi = 0.0
    else:
        phi = float(np.arctan2(inward[0] * m[1] - inward[1] * m[0], inward @ m))
    width = 2 * np.pi / N_SECTORS
    sector = int(np.floor((phi + width / 2) / width)) % N_SECTORS
    return face, sector


def push_line_behaviour(steps: Sequence[TaskStep]) -> int | None:
    """``6 · face + sector`` of the first executed primitive, or None when every one was refused."""
    for step in steps:
        if step.executed:
            face, sector = push_face_and_sector(step)
            return N_SECTORS * face + sector
    return None


# --- push-align ----------------------------------------------------------------------------------
ALIGN_GOAL = (0.10, 0.0, np.pi / 4)  # x, y (m), yaw (rad)
ALIGN_OBSTACLE = Obstacle(centre=(0.0, 0.0, 0.03), half_size=(0.02, 0.04, 0.03))


def _push_align_goal(pos: np.ndarray, quat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return np.array([ALIGN_GOAL[0], ALIGN_GOAL[1], CUBE_HALF_M]), yaw_quat(ALIGN_GOAL[2])


def push_align_behaviour(steps: Sequence[TaskStep]) -> int | None:
    """0 (upper) / 1 (lower): the side of the obstacle's centre line y = y_obs where the cube's centre
    first crosses x = x_obs; None if it never does."""
    if not steps:
        return None
    ox, oy = ALIGN_OBSTACLE.centre[:2]
    xy = [np.asarray(steps[0].pose_before[:2], dtype=np.float64)]
    xy += [np.asarray(s.pose_after[:2], dtype=np.float64) for s in steps]
    for a, b in zip(xy[:-1], xy[1:], strict=True):
        da, db = a[0] - ox, b[0] - ox
        if not ((da < 0 <= db) or (db <= 0 < da)):
            continue  # the centre does not reach or cross x = ox between these two poses
        y = a[1] + (b[1] - a[1]) * (ox - a[0]) / (b[0] - a[0])
        return 0 if y > oy else 1
    return None


TASKS: dict[str, Task] = {
    "push-line": Task(
        name="push-line",
        summary="push the cube across the line y = 0; behaviour = pushed face x motion sector (24)",
        n_behaviours=N_FACES * N_SECTORS,
        start=(0.0, -0.08, 0.0),
        start_region=((-0.12, 0.12), (-0.16, -0.04)),
        goal=_push_line_goal,
        goal_follows_object=True,
        behaviour=push_line_behaviour,
        behaviour_names=tuple(f"face {f} sector {s}" for f in FACE_NAMES for s in range(N_SECTORS)),
    ),
    "push-align": Task(
        name="push-align",
        summary="push the cube around an obstacle to a pose turned by 45 deg; behaviour = upper/lower path (2)",
        n_behaviours=2,
        start=(-0.10, 0.0, 0.0),
        start_region=((-0.13, -0.08), (-0.08, 0.08)),
        goal=_push_align_goal,
        goal_follows_object=False,
        behaviour=push_align_behaviour,
        obstacles=(ALIGN_OBSTACLE,),
        behaviour_names=("upper", "lower"),
    ),
}
TASK_NAMES = tuple(TASKS)
#: ``--task``: the names of ``TASKS``.
TaskName = Enum("TaskName", {name.replace("-", "_"): name for name in TASKS}, type=str)


def get_task(name: str) -> Task:
    if name not in TASKS:
        raise ValueError(f"`task` must be one of {list(TASKS)}. Got {name!r}.")
    return TASKS[name]


def behaviour_entropy(ids, n_behaviours: int, axis: int = -1) -> np.ndarray | float:
    """Normalised behaviour entropy ``−Σ_b π(b) log_|B| π(b)`` of behaviour ids along ``axis``.

    ``ids``: integer ids in ``range(n_behaviours)``; negative ids (episodes without a behaviour) are
    left out of ``π``. No behaviour at all gives 0. Vectorised: ``ids (..., n)`` → ``(...)``.
    """
    if n_behaviours < 2:
        raise ValueError(f"`n_behaviours` must be at least 2. Got {n_behaviours}.")
    a = np.moveaxis(np.asarray(ids), axis, -1)
    counts = (a[..., None] == np.arange(n_behaviours)).sum(axis=-2)  # (..., |B|)
    total = counts.sum(axis=-1, keepdims=True)
    p = counts / np.maximum(total, 1)
    with np.errstate(divide="ignore", invalid="ignore"):
        terms = np.where(p > 0, p * np.log(np.where(p > 0, p, 1.0)), 0.0)
    h = -terms.sum(axis=-1) / np.log(n_behaviours)
    h = np.maximum(h, 0.0)  # -0.0 and rounding below zero
    return float(h) if np.ndim(h) == 0 else h
