"""Object symmetries: the rotations under which an object's surface maps onto itself.

A depth camera cannot tell a cylinder from the same cylinder rolled about its axis, a box from the
box turned 180°, a cube from the cube turned 90°. Goals are therefore reached *up to the object's
symmetry* (``sim.contract.symmetric_goal``): the goal flow points to the nearest of the poses that
look exactly like the goal pose, the reward and success use that flow, and the robot's registration,
which sees only geometry, measures the same quantity. Without it the training env demanded, and its
mesh observation (exact point correspondences) showed, a roll or turn no camera can see, and the twin
lost those episodes (docs/results.md, the sim → twin ladder).

:func:`symmetries` finds the group numerically (``(S, 4, 4)`` transforms in the object frame,
identity first), so no per-object annotation is needed: candidate rotations about the surface's
bounding-box centre (about each principal axis in 10° steps, and those composed with a quarter or half turn
about another principal axis: cube, box, cylinder end-over-end flips, hexagonal prisms) are kept
when the rotated surface samples lie on the surface (their distances to the nearest sample, against
the samples' own spacing: ``MEAN_TOL``, ``TAIL_TOL``). The object frame's axes are candidates too (a
cube's principal axes are arbitrary). Continuous symmetries come out as their 10° steps: a flow
to the nearest step is off by at most 5° of turn (3 mm at a 3.5 cm radius). Results are cached on
disk like the stable poses (``HYDO_CACHE``), keyed by the geometry; those of the built-in objects
ship in ``sim/assets/symmetries.npz`` (``python -m sim.symmetry`` regenerates it, ~1 min).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.atomic import atomic_write
from sim.objects import (
    ObjectAsset,
    builtin_objects,
    cache_root,
    extra_train_objects,
    geometry_hash,
    varied_train_objects,
)

SHIPPED_FILE = Path(__file__).parent / "assets" / "symmetries.npz"  # `python -m sim.symmetry`

STEP_DEG = 10.0
# accepted: the rotated samples' distances to the nearest sample, in units of the samples' own
# spacing, have mean ≤ MEAN_TOL and 98th percentile ≤ TAIL_TOL (exact symmetries measure ~1.1 / ~2.3;
# a box turned 90° 2.7 / 4.7; a mug turned 40° 1.5 / 7.8, its handle off the surface)
MEAN_TOL = 1.3
TAIL_TOL = 2.6
CHECK_POINTS = 1024  # surface samples rotated per candidate
SAME_DEG = 3.0  # candidates closer than this to an accepted one are the same rotation


def _axis_rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` (rad) about the unit ``axis`` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * (k @ k)


def candidate_rotations(axes: np.ndarray) -> np.ndarray:
    """(C, 3, 3) rotations to test, from a frame's ``axes`` (3 unit vectors, rows): about each axis
    in ``STEP_DEG`` steps, alone and after a quarter, half or three-quarter turn about another."""
    angles = np.deg2rad(np.arange(0.0, 360.0, STEP_DEG))
    single = [_axis_rotation(a, t) for a in axes for t in angles]
    turns = [_axis_rotation(axes[j], np.deg2rad(d)) for j in range(3) for d in (90.0, 180.0, 270.0)]
    composed = [
        _axis_rotation(axes[k], t) @ turn
        for k in range(3)
        for t in angles
        for j, turn in enumerate(turns)
        if j // 3 != k
    ]
    return np.array(single + composed)


def find_symmetries(points: np.ndarray) -> np.ndarray:
    """``(S, 4, 4)`` transforms (object frame, identity first) mapping the surface samples
    ``points (P, 3)`` onto themselves, rotations about their bounding-box centre."""
    from scipy.spatial import cKDTree

    points = np.asarray(points, dtype=np.float64)
    tree = cKDTree(points)
    spacing = float(tree.query(points, k=2)[0][:, 1].mean())  # the samples' own nearest-neighbour gap
    # the centre: the samples' bounding-box centre (their mean is off a cylinder's axis by the
    # sampling noise, ~1 mm, which a half turn doubles: enough to reject a true symmetry)
    c = (points.min(0) + points.max(0)) / 2
    rng = np.random.default_rng(0)
    probe = points[rng.choice(len(points), min(CHECK_POINTS, len(points)), replace=False)] - c
    # the principal axes, and the object frame's own (a cube's principal axes are arbitrary)
    _, vecs = np.linalg.eigh(np.cov((points - c).T))
    Rs = np.concatenate([candidate_rotations(vecs.T), candidate_rotations(np.eye(3))])  # (C, 3, 3)
    moved = np.einsum("cij,pj->cpi", Rs, probe) + c  # (C, P, 3)
    d = tree.query(moved.reshape(-1, 3))[0].reshape(len(Rs), -1) / spacing  # (C, P)
    ok = (d.mean(1) <= MEAN_TOL) & (np.quantile(d, 0.98, axis=1) <= TAIL_TOL)
    accepted = [np.eye(3)]
    cos_same = np.cos(np.deg2rad(SAME_DEG))
    for i in np.flatnonzero(ok)[np.argsort(d.mean(1)[ok])]:
        if all((np.trace(Rs[i] @ R.T) - 1) / 2 < cos_same for R in accepted):
            accepted.append(Rs[i])
    out = np.tile(np.eye(4), (len(accepted), 1, 1))
    for k, R in enumerate(accepted):
        out[k, :3, :3] = R
        out[k, :3, 3] = c - R @ c  # about the centre
    return out


def _cache_path(asset: ObjectAsset):
    return cache_root() / "symmetries" / f"{asset.name}-{geometry_hash(asset)}.npz"


_CACHE: dict[str, np.ndarray] = {}


def symmetries(asset: ObjectAsset) -> np.ndarray:
    """The ``(S, 4, 4)`` symmetry transforms of ``asset`` (object frame, identity first): shipped,
    cached in memory and on disk, or computed now (~1 s)."""
    key = f"{asset.name}-{geometry_hash(asset)}"
    if not _CACHE and SHIPPED_FILE.exists():
        _CACHE.update(dict(np.load(SHIPPED_FILE)))
    if key in _CACHE:
        return _CACHE[key]
    path = _cache_path(asset)
    out = None
    if path.exists():
        try:
            out = np.load(path)["transforms"]
        except (OSError, ValueError, KeyError):
            out = None  # a damaged cache file is recomputed
    if out is None:
        out = find_symmetries(asset.surface_points)
        path.parent.mkdir(parents=True, exist_ok=True)
        atomic_write(path, lambda f: np.savez(f, transforms=out))
    _CACHE[key] = out
    return out


def main() -> None:
    """``python -m sim.symmetry``: the shipped symmetries of every built-in, ``train-extra`` and
    ``train-varied`` object (entries already shipped are kept; ``--recompute`` recomputes them)."""
    import sys

    shipped = (
        {} if "--recompute" in sys.argv[1:] or not SHIPPED_FILE.exists() else dict(np.load(SHIPPED_FILE))
    )
    arrays = {}
    for asset in builtin_objects() + extra_train_objects() + varied_train_objects():
        key = f"{asset.name}-{geometry_hash(asset)}"
        arrays[key] = shipped[key] if key in shipped else find_symmetries(asset.surface_points)
        print(f"{asset.name}: {len(arrays[key])} symmetries")
    atomic_write(SHIPPED_FILE, lambda f: np.savez_compressed(f, **arrays))
    print(f"wrote {SHIPPED_FILE} ({len(arrays)} objects)")


if __name__ == "__main__":
    main()
