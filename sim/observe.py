"""Observation sources: segmented point clouds from the simulated scene.

Two sources share one interface, ``segmented_clouds(scene) -> (obj_points, obj_normals, bg_points)``,
and ``sim.contract.build_observation`` turns either into the network's fixed-size observation:

- ``MeshObserver`` (training default, ~1 ms): the object's mesh-surface samples transformed by its
  simulated pose, keeping the ones the scene's depth cameras see: not facing the floor, not touching
  it, and not behind the object's own surface in all three cameras (a z-buffer of the samples, the
  same test registration runs on goal clouds); the background is a fixed grid on the bin's floor and
  inner walls plus clutter surfaces.
- ``RenderObserver`` (``sim.render``): three rendered depth cameras with background subtraction,
  the sim2real-like path also used by deploy's twin.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from sim.contract import transform_points
from sim.depth import pinhole_intrinsics, seen_from_cameras
from sim.primitive import BIN_FLOOR_Z, BIN_INNER_SIZE_M

#: The scene's depth cameras (sim/assets/scene.xml) and their image size: what the rendered
#: observation renders and what the mesh observation's z-buffer projects into.
CAMERAS = ("cam_front", "cam_left", "cam_right")
DEPTH_HEIGHT, DEPTH_WIDTH = 240, 320  # pixels; at 120x160 too few object pixels remain

HIDDEN_NORMAL_Z = -0.3  # points whose normal points further down than this face the floor: unseen
FLOOR_CONTACT_M = 0.006  # points this close to the floor are lost: under the object, or in the background
BG_GRID_M = 0.015  # spacing of the bin's background grid
MIN_VISIBLE_POINTS = 8  # fewer visible samples than this (e.g. mid-air): keep them all instead

# MuJoCo cameras look along -z with y up; OpenCV's optical frame looks along +z with y down.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def camera_pose_cv(data: mujoco.MjData, cam_id: int) -> np.ndarray:
    """Pose (4, 4) of camera ``cam_id``'s OpenCV optical frame in the world (after mj_forward)."""
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cam_id].reshape(3, 3) @ _GL_TO_CV
    T[:3, 3] = data.cam_xpos[cam_id]
    return T


def scene_cameras(model: mujoco.MjModel, cameras=CAMERAS, height=DEPTH_HEIGHT, width=DEPTH_WIDTH) -> list:
    """``[(K (3, 3), T_world_cam (4, 4), (height, width))]`` of the scene's depth cameras, the form
    ``sim.depth.seen_from_cameras`` takes. They look at the static bin, so any state gives the same
    poses: a scratch ``MjData`` at the model's defaults is forwarded once."""
    d = mujoco.MjData(model)
    mujoco.mj_forward(model, d)
    out = []
    for name in cameras:
        i = model.camera(name).id
        out.append(
            (pinhole_intrinsics(model.cam_fovy[i], width, height), camera_pose_cv(d, i), (height, width))
        )
    return out


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


def visible_mask(normals_obj: np.ndarray, T: np.ndarray, points_world: np.ndarray) -> np.ndarray:
    """(S,) bool: the samples not facing the floor and not touching it (``HIDDEN_NORMAL_Z``,
    ``FLOOR_CONTACT_M``), given their object-frame normals (S, 3), the pose ``T`` and the samples
    at that pose (S, 3)."""
    n_z = normals_obj @ T[2, :3]  # the world z of each normal
    return (n_z > HIDDEN_NORMAL_Z) & (points_world[:, 2] > BIN_FLOOR_Z + FLOOR_CONTACT_M)


def visible_surface(
    points_obj: np.ndarray, normals_obj: np.ndarray, T: np.ndarray, points_world: np.ndarray | None = None
):
    """Surface samples (S, 3) and normals (S, 3) in the object frame -> those not facing or touching
    the floor, world frame (``camera_visible_surface`` without cameras: clutter, render fallbacks).
    ``points_world``: the samples at ``T`` (``transform_points(T, points_obj)``) if the caller has them."""
    return camera_visible_surface(points_obj, normals_obj, T, [], points_world)


def camera_visible_surface(
    points_obj: np.ndarray,
    normals_obj: np.ndarray,
    T: np.ndarray,
    cameras: list,
    points_world: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The training observation's object cloud: the samples (S, 3) / normals (S, 3) in the object
    frame -> those some camera sees at pose ``T``, bin frame (floor at z = 0), metres.

    With ``cameras``: the samples not touching the floor that face one of the cameras and lie in
    front in its view, the z-buffer of the object's own samples (``sim.depth.seen_from_cameras``'
    form, bin frame). Without (or fewer than ``MIN_VISIBLE_POINTS`` seen): ``visible_surface``'s
    test (not facing the floor, not touching it), then every sample (a degenerate view)."""
    p = transform_points(T, points_obj) if points_world is None else points_world
    n = normals_obj @ T[:3, :3].T
    keep = visible_mask(normals_obj, T, p)
    if cameras:
        # with cameras, what faces one of them and is in front in its view, whatever the normal's
        # tilt: a flared bowl's outer wall faces down and out, and the cameras see it
        seen = (p[:, 2] > BIN_FLOOR_Z + FLOOR_CONTACT_M) & seen_from_cameras(p, None, cameras, normals=n)
        if seen.sum() >= MIN_VISIBLE_POINTS:
            keep = seen
    if keep.sum() < MIN_VISIBLE_POINTS:
        keep = np.ones(len(p), bool)
    return p.compress(keep, axis=0), n.compress(keep, axis=0)


class MeshObserver:
    """Segmented clouds from mesh-surface samples and the simulated poses (no rendering).

    ``cameras=True`` (the default) keeps only the samples the scene's depth cameras see (the
    z-buffer above); ``False`` keeps every sample not facing or touching the floor, which shows the
    policy surfaces no camera in the cell sees (the observation of models trained before the
    z-buffer, kept to measure them: ``bench/render_gap.py``)."""

    def __init__(self, cameras: bool = True):
        self.cameras = bool(cameras)
        self.name = "mesh" if self.cameras else "mesh-all"
        self._views: tuple[mujoco.MjModel, list] | None = None  # (model, scene_cameras(model))

    def _scene_views(self, model: mujoco.MjModel) -> list:
        if self._views is None or self._views[0] is not model:
            self._views = (model, scene_cameras(model))
        return self._views[1]

    def segmented_clouds(self, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(obj_points (M, 3), obj_normals (M, 3), bg_points (L, 3))`` world frame, metres."""
        views = self._scene_views(scene.model) if self.cameras else []
        obj_p, obj_n = camera_visible_surface(
            scene.asset.surface_points,
            scene.asset.surface_normals,
            scene.object_T(),
            views,
            scene.object_surface(),
        )
        bg = [bin_background_points()]
        for i, c in enumerate(scene.clutter):
            bg.append(visible_surface(c.surface_points, c.surface_normals, scene.object_T(f"clutter{i}"))[0])
        bg.extend(ob.surface_points() for ob in getattr(scene, "obstacles", ()))  # static task boxes
        return obj_p, obj_n, np.concatenate(bg) if len(bg) > 1 else bg[0]
