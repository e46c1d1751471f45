"""Stable poses by drop-and-settle, and episode sampling (HACMan's ``planar`` and ``6d`` goal modes).

A stable pose is stored as ``(z, qw, qx, qy, qz)``: the object origin's height above the bin floor
(metres) and its orientation. Any yaw about the world z axis and any x, y inside the bin keep it
stable, so goals re-sample both.

Built-in objects use the shipped ``assets/stable_poses.npz`` (regenerate with
``python -m sim.goals``); user meshes are computed on first use (with a progress bar) and cached under
``$HYDO_CACHE`` (default ``~/.cache/hydo``). Both caches are keyed by a hash of the object's geometry,
so a changed mesh never reuses stale poses.

Episodes (an object, its start and its goal) are drawn here, in one place, for the training env
(``sim.env.BinEnv.reset``) and the deploy twin (``robot.twin.sample_episode``): :func:`sample_object`,
then :func:`sample_start_and_goal`, in the bin frame (origin at the centre of the bin floor's top).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.atomic import atomic_write
from sim.contract import pose_matrix, symmetric_goal, transform_points
from sim.objects import (
    ObjectAsset,
    builtin_objects,
    cache_root,
    extra_train_objects,
    geometry_hash,
    varied_train_objects,
)
from sim.primitive import BIN_INNER_SIZE_M
from sim.symmetry import symmetries

N_STABLE_POSES = 100
SHIPPED_FILE = Path(__file__).parent / "assets" / "stable_poses.npz"
DROP_HEIGHT_M = 0.15  # object origin's drop height above the floor
STABLE_MAX_MOVE_M = 0.005  # a stable pose moves less than this ...
STABLE_MAX_TURN_RAD = np.deg2rad(3.0)  # ... and turns less than this over 1 s
WALL_MARGIN_M = 0.02  # keep sampled object footprints this far from the bin walls
#: Start and goal positions of the object's origin are drawn from this central region (half-sizes,
#: metres), as HACMan drops objects above the bin's centre: the Panda palm is 20 cm wide, so a hand
#: between an object and a wall needs room that the outer 10 cm of the bin does not have.
PLACEMENT_HALF_M = np.array([0.12, 0.14])
MIN_GOAL_DISTANCE_M = 0.05  # a goal must start further than the success threshold (with margin)
GOAL_TRIES = 100  # start/goal pairs drawn before the last one is kept, however close
#: A 6D goal that tilts the object's up direction by this much or more (up to its symmetry) counts as a
#: flip (another face up); under it, a move. Poses on one face differ by yaw only (tilt ~0; a
#: near-symmetry may add ~10°), poses on two faces by the angle between the faces.
FLIP_TILT_DEG = 30.0


def random_quaternion(rng: np.random.Generator) -> np.ndarray:
    """Uniform random unit quaternion (4,) wxyz (Shoemake)."""
    u1, u2, u3 = rng.random(3)
    a, b = np.sqrt(1 - u1), np.sqrt(u1)
    return np.array(
        [
            b * np.cos(2 * np.pi * u3),
            a * np.sin(2 * np.pi * u2),
            a * np.cos(2 * np.pi * u2),
            b * np.sin(2 * np.pi * u3),
        ]
    )


def quat_mul(q1: np.ndarray, q2: np.ndarray) -> np.ndarray:
    """Hamilton product q1 ⊗ q2 of wxyz quaternions."""
    w1, x1, y1, z1 = q1
    w2, x2, y2, z2 = q2
    return np.array(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ]
    )


def quat_angle(q1: np.ndarray, q2: np.ndarray) -> float:
    """Rotation angle (rad) between two unit quaternions."""
    return float(2 * np.arccos(np.clip(abs(np.dot(q1, q2)), -1.0, 1.0)))


def yaw_quat(yaw: float) -> np.ndarray:
    return np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)])


def compute_stable_poses(
    asset: ObjectAsset, n: int = N_STABLE_POSES, seed: int = 0, progress=None
) -> np.ndarray:
    """Drop ``asset`` from random orientations and keep ``n`` rest poses that stay put for 1 s.

    Returns ``(n, 5)`` float64 rows ``(z, qw, qx, qy, qz)``. ``progress(i, n)`` is called per pose.
    """
    import mujoco

    from sim.scene import BinScene  # local: mujoco is only needed to compute, not to load

    scene = BinScene(asset)
    rng = np.random.default_rng(seed)
    dt = scene.model.opt.timestep
    out: list[np.ndarray] = []
    attempts = 0
    while len(out) < n:
        attempts += 1
        if attempts > 5 * n:
            raise RuntimeError(f"{asset.name}: only {len(out)} of {n} drops came to a stable rest")
        scene.set_object_pose(np.array([0.0, 0.0, DROP_HEIGHT_M]), random_quaternion(rng))
        scene.settle(max_s=3.0)
        pos, quat = scene.object_pose()
        # Verify: restart exactly at that pose with zero velocity and watch it for 1 s.
        scene.set_object_pose(pos, quat)
        mujoco.mj_step(scene.model, scene.data, nstep=int(round(1.0 / dt)))
        pos1, quat1 = scene.object_pose()
        if np.linalg.norm(pos1 - pos) < STABLE_MAX_MOVE_M and quat_angle(quat, quat1) < STABLE_MAX_TURN_RAD:
            out.append(np.concatenate([[pos[2]], quat]))
            if progress is not None:
                progress(len(out), n)
    return np.stack(out)


def _cache_dir() -> Path:
    return cache_root() / "stable_poses"


def _atomic_savez(path: Path, **arrays) -> None:
    atomic_write(path, lambda f: np.savez_compressed(f, **arrays))


_SHIPPED: dict[str, np.ndarray] | None = None


def stable_poses(asset: ObjectAsset, progress=None) -> np.ndarray:
    """The ``(n, 5)`` stable poses of ``asset``: shipped, cached, or computed now (with progress: a bar
    of its own, or ``progress(i, n)`` per pose from a caller that shows its own)."""
    global _SHIPPED
    key = f"{asset.name}-{geometry_hash(asset)}"
    if _SHIPPED is None:
        _SHIPPED = dict(np.load(SHIPPED_FILE)) if SHIPPED_FILE.exists() else {}
    if key in _SHIPPED:
        return _SHIPPED[key]
    path = _cache_dir() / f"{key}.npz"
    if path.exists():
        return np.load(path)["poses"]
    if progress is not None:
        poses = compute_stable_poses(asset, progress=progress)
    else:
        from rich.progress import Progress

        with Progress(transient=True) as bar:
            task = bar.add_task(f"stable poses of {asset.name}", total=N_STABLE_POSES)
            poses = compute_stable_poses(asset, progress=lambda i, n: bar.update(task, completed=i))
    _atomic_savez(path, poses=poses)
    return poses


def footprint_radius(asset: ObjectAsset, quat_wxyz: np.ndarray) -> float:
    """Largest horizontal distance (m) of the object's surface from its origin in orientation ``quat``."""
    R = pose_matrix(np.zeros(3), quat_wxyz)[:3, :3]
    return float(np.linalg.norm((asset.surface_points @ R.T)[:, :2], axis=1).max())


def sample_placement(
    asset: ObjectAsset, pose: np.ndarray, rng: np.random.Generator, yaw: float | None = None
):
    """Place stable ``pose`` (5,) at a random yaw and bin position: returns ``(pos (3,), quat (4,))``."""
    yaw = rng.uniform(-np.pi, np.pi) if yaw is None else yaw
    quat = quat_mul(yaw_quat(yaw), pose[1:5])
    r = footprint_radius(asset, quat)
    half = np.minimum(np.maximum(BIN_INNER_SIZE_M[:2] / 2 - r - WALL_MARGIN_M, 0.0), PLACEMENT_HALF_M)
    xy = rng.uniform(-half, half)
    return np.array([xy[0], xy[1], pose[0]]), quat


def sample_object(assets, rng: np.random.Generator) -> ObjectAsset:
    """A uniformly random object of ``assets`` (one ``rng.integers`` draw)."""
    return assets[rng.integers(len(assets))]


def sample_start_and_goal(
    asset: ObjectAsset,
    goal_mode: str,
    rng: np.random.Generator,
    poses: np.ndarray | None = None,
    symmetric: bool = True,
    flip: bool | None = None,
):
    """A start and a goal of ``asset`` in the bin frame: ``((pos, quat), (goal_pos, goal_quat))``.

    The start is a random stable pose (of ``poses``, default :func:`stable_poses`) at a random yaw and
    bin position; ``planar`` goals translate it (same stable pose and yaw), ``6d`` goals pick another
    stable pose, yaw and position. A pair whose goal is within ``MIN_GOAL_DISTANCE_M`` (mean distance
    of the surface samples, up to the object's symmetry unless ``symmetric=False``:
    ``sim.contract.symmetric_goal``) is re-drawn, up to ``GOAL_TRIES`` times (then the last pair is kept).
    ``flip`` (6D goals; None: either): re-draw also until the goal is a flip (True: tilt ≥
    ``FLIP_TILT_DEG``) or a move (False); an object that :func:`can_flip` says cannot keeps its last
    pair after ``GOAL_TRIES`` draws (ask it with ``flip=None`` instead).
    """
    poses = stable_poses(asset) if poses is None else poses
    sym = symmetries(asset) if symmetric else None  # (S, 4, 4), looked up once, not per draw
    for _ in range(GOAL_TRIES):
        start = poses[rng.integers(len(poses))]
        yaw = rng.uniform(-np.pi, np.pi)
        pos, quat = sample_placement(asset, start, rng, yaw=yaw)
        if goal_mode == "planar":  # same stable pose and yaw: a pure translation
            gpos, gquat = sample_placement(asset, start, rng, yaw=yaw)
        else:
            gpos, gquat = sample_placement(asset, poses[rng.integers(len(poses))], rng)
        # the distance the episode starts at, up to the object's symmetry (as the reward measures
        # it): a 6D goal that is the start turned by a symmetry is no goal at all
        T_start = pose_matrix(pos, quat)
        T_goal = pose_matrix(gpos, gquat)
        if symmetric:
            T_goal = symmetric_goal(T_start, T_goal, asset.surface_points, sym)
        d = np.linalg.norm(
            transform_points(T_goal, asset.surface_points) - transform_points(T_start, asset.surface_points),
            axis=1,
        ).mean()
        if flip is not None:  # up to the symmetry the goal is reached up to, as can_flip
            flipped = tilt_deg(T_start, T_goal, sym) >= FLIP_TILT_DEG
        if d > MIN_GOAL_DISTANCE_M and (flip is None or flipped == flip):
            break
    return (pos, quat), (gpos, gquat)


def can_flip(asset: ObjectAsset, poses: np.ndarray | None = None, symmetric: bool = True) -> bool:
    """Whether some 6D goal of ``asset`` is a flip: two of its stable ``poses`` (rows ``(z, qw, qx, qy,
    qz)``, default :func:`stable_poses`) whose up directions differ by ``FLIP_TILT_DEG`` or more under
    every symmetry the goal may be reached up to (``symmetric``). A cube cannot flip (each face is
    another up to its symmetry); a box can. What ``sample_start_and_goal(flip=True)`` needs to find one.

    Yaw and position do not enter (tilt is the angle between the world's up seen in the object's frame
    at the two poses), so the answer is one per asset: one (S, P, P) product of up directions.
    """
    poses = stable_poses(asset) if poses is None else poses
    up = np.stack([pose_matrix(np.zeros(3), q)[2, :3] for q in poses[:, 1:5]])  # (P, 3) world z, object frame
    sym_R = symmetries(asset)[:, :3, :3] if symmetric else np.eye(3)[None]  # (S, 3, 3) object frame
    # tilt_deg for every pair at once (100 poses: 10^4 pairs): the goal pose R_j S has up S^T u_j in
    # the object frame, so cos(tilt) = (S u_i) . u_j, and the least tilt is the largest cosine
    cos = np.einsum("sab,ib,ja->sij", sym_R, up, up).max(axis=0)  # (P, P): the least tilt over S
    return bool((cos < np.cos(np.deg2rad(FLIP_TILT_DEG))).any())


def tilt_deg(T_from: np.ndarray, T_to: np.ndarray, symmetries: np.ndarray | None = None) -> float:
    """Degrees between an object's up direction at two (4, 4) poses in one frame: ~0 when they differ
    by a move and a yaw, ~90 or ~180 when they rest on different faces.

    ``symmetries (S, 4, 4)`` (object frame): the least tilt to any of ``T_to · S``. Those poses put the
    same surface in the same place, so a goal that is the start turned over by a symmetry (a U-prism
    or a torus upside down, a capsule rolled about its axis) shows the same face: a move, not a flip,
    whichever of them the reward's nearest pose happens to be."""
    R_to = T_to[:3, :3] if symmetries is None else T_to[:3, :3] @ symmetries[:, :3, :3]  # (3, 3) | (S, 3, 3)
    # R_to[..., 2, :] is the world's up in the object frame at the goal (T_from[2, :3] at the start)
    cos = float(np.max(R_to[..., 2, :] @ T_from[2, :3]))
    return float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def episode_seed(seed: int, i: int) -> int:
    """The seed of episode ``i`` of an evaluation with seed ``seed``: ``hydo eval`` resets its env with
    it and ``hydo deploy --robot sim`` draws its twin episode from it, so both face the same objects,
    start poses and goals."""
    return seed * 1_000_003 + i


def sample_episode(assets, goal_mode: str, rng: np.random.Generator, poses: dict | None = None):
    """:func:`sample_object`, then :func:`sample_start_and_goal`: ``(asset, start, goal)``, bin frame.

    ``poses``: optional ``{name: stable poses}`` cache.
    """
    asset = sample_object(assets, rng)
    start, goal = sample_start_and_goal(asset, goal_mode, rng, None if poses is None else poses[asset.name])
    return asset, start, goal


def main(argv: list[str] | None = None) -> None:
    """``python -m sim.goals``: compute the shipped stable poses of every built-in, ``train-extra`` and ``train-varied``
    object missing from the shipped file (``--recompute``: all of them; deterministic, ~1 s per
    object; entries already shipped are kept, so the episodes behind earlier figures do not move
    with another CPU's rounding); ``python -m sim.goals MESH_OR_FOLDER ...``: compute and cache those of
    user meshes ahead of training (what ``--objects FOLDER`` would do on first use), with a bar per
    object and one over all of them."""
    import argparse

    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

    from sim.objects import ObjectMeshError, load_objects

    ap = argparse.ArgumentParser(prog="python -m sim.goals", description=main.__doc__.splitlines()[0])
    ap.add_argument("meshes", nargs="*", help="user .obj/.stl files or folders of them (default: built-ins)")
    ap.add_argument("--recompute", action="store_true", help="recompute shipped entries too")
    args = ap.parse_args(argv)
    try:
        if args.meshes:
            assets = [a for spec in args.meshes for a in load_objects(spec)]
        else:
            assets = list(builtin_objects() + extra_train_objects() + varied_train_objects())
    except (ValueError, ObjectMeshError) as e:  # a bad path or mesh: one line, no traceback
        ap.exit(1, f"python -m sim.goals: error: {e}\n")
    shipped = {} if args.recompute or not SHIPPED_FILE.exists() else dict(np.load(SHIPPED_FILE))
    arrays = {}
    columns = (TextColumn("{task.description:<32}"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn())
    with Progress(*columns) as bar:
        overall = bar.add_task("objects", total=len(assets))
        for asset in assets:
            key = f"{asset.name}-{geometry_hash(asset)}"
            if not args.meshes and key in shipped:
                arrays[key] = shipped[key]
                bar.advance(overall)
                continue
            task = bar.add_task(f"  {asset.name}", total=N_STABLE_POSES)

            def tick(i, n, task=task):
                bar.update(task, completed=i, total=n)

            if args.meshes:  # cached under $HYDO_CACHE, where training looks them up
                stable_poses(asset, progress=tick)
            else:
                arrays[key] = compute_stable_poses(asset, progress=tick)
            bar.update(task, completed=N_STABLE_POSES)
            bar.advance(overall)
    if args.meshes:
        print(f"stable poses of {len(assets)} objects cached in {_cache_dir()}")
    else:
        _atomic_savez(SHIPPED_FILE, **arrays)
        print(f"wrote {SHIPPED_FILE} ({len(arrays)} objects)")


if __name__ == "__main__":
    main()
