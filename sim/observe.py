"""Observation sources: segmented point clouds from the simulated scene.

Two sources share one interface, ``segmented_clouds(scene) -> (obj_points, obj_normals, bg_points)``,
and ``sim.contract.build_observation`` turns either into the network's fixed-size observation:

- ``MeshObserver`` (training default, ~0.1 ms): the object's mesh-surface samples transformed by its
  simulated pose, dropping points the cameras cannot see (facing the floor, or touching it); the
  background is a fixed grid on the bin's floor and inner walls plus clutter surfaces.
- ``RenderObserver`` (``sim.render``): three rendered depth cameras with background subtraction,
  the sim2real-like path also used by deploy's twin.
"""

from __future__ import annotations

import functools

import numpy as np

from sim.contract import transform_points
from sim.primitive import BIN_FLOOR_Z, BIN_INNER_SIZE_M

HIDDEN_NORMAL_Z = -0.3  # points whose normal points further down than this face the floor: unseen
FLOOR_CONTACT_M = 0.003  # points this close to the floor are hidden under the object
BG_GRID_M = 0.015  # spacing of the bin's background grid


@functools.cache
def bin_background_points() -> np.ndarray:
    """Grid points (L, 3) float32 on the bin floor and the inner faces of its four walls."""
    hx, hy, h = BIN_INNER_SIZE_M[0] / 2, BIN_INNER_SIZE_M[1] / 2, BIN_INNER_SIZE_M[2]
    xs = np.arange(-hx, hx + 1e-9, BG_GRID_M)
    ys = np.arange(-hy, hy + 1e-9, BG_GRID_M)
    zs = np.arange(BIN_FLOOR_Z, BIN_FLOOR_Z + h + 1e-9, BG_GRID_M)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    floor = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, BIN_FLOOR_Z)], 1)
    walls = []
    for x in (-hx, hx):
        a, b = np.meshgrid(ys, zs, indexing="ij")
        walls.append(np.stack([np.full(a.size, x), a.ravel(), b.ravel()], 1))
    for y in (-hy, hy):
        a, b = np.meshgrid(xs, zs, indexing="ij")
        walls.append(np.stack([a.ravel(), np.full(a.size, y), b.ravel()], 1))
    return np.concatenate([floor, *walls]).astype(np.float32)


def visible_surface(
    points_obj: np.ndarray, normals_obj: np.ndarray, T: np.ndarray, points_world: np.ndarray | None = None
):
    """Surface samples (S, 3) and normals (S, 3) in the object frame -> the visible ones, world frame.
    ``points_world``: the samples at ``T`` (``transform_points(T, points_obj)``) if the caller has them."""
    p = transform_points(T, points_obj) if points_world is None else points_world
    n = normals_obj @ T[:3, :3].T
    keep = (n[:, 2] > HIDDEN_NORMAL_Z) & (p[:, 2] > BIN_FLOOR_Z + FLOOR_CONTACT_M)
    if keep.sum() < 8:  # degenerate view (e.g. mid-air): fall back to everything rather than nothing
        return p.copy(), n  # a copy, as p[keep] would be (points_world may be a cache)
    return p.compress(keep, axis=0), n.compress(keep, axis=0)  # p[keep], several times faster


class MeshObserver:
    """Segmented clouds from mesh-surface samples and the simulated poses (no rendering)."""

    name = "mesh"

    def segmented_clouds(self, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(obj_points (M, 3), obj_normals (M, 3), bg_points (L, 3))`` world frame, metres."""
        obj_p, obj_n = visible_surface(
            scene.asset.surface_points, scene.asset.surface_normals, scene.object_T(), scene.object_surface()
        )
        bg = [bin_background_points()]
        for i, c in enumerate(scene.clutter):
            bg.append(visible_surface(c.surface_points, c.surface_normals, scene.object_T(f"clutter{i}"))[0])
        bg.extend(ob.surface_points() for ob in getattr(scene, "obstacles", ()))  # static task boxes
        return obj_p, obj_n, np.concatenate(bg) if len(bg) > 1 else bg[0]
