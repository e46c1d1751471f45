"""Rendered observations (three depth cameras + background subtraction), RGB frames and videos.

Two layers live here:

1. **Pure image processing** (numpy + OpenCV + scipy, no MuJoCo): :func:`pinhole_intrinsics`,
   :func:`backproject`, :func:`background_from_frames`, :func:`subtract_background`,
   :func:`estimate_normals`, :func:`crop_box`, :func:`mask_iou` and the whole per-frame pipeline
   :func:`clouds_from_depth`. This is their one home: deploy (``robot/``, torch-free) imports
   exactly these functions for real RealSense frames, so a depth frame is segmented and lifted to a
   cloud the same way in simulation and on the robot. Their frames follow OpenCV: the camera's
   optical frame has x right, y down and z forward (into the scene), depth is the z coordinate in
   that frame (metres, as a RealSense reports it), pixel ``(row v, column u)`` has its centre at
   ``(u, v)``.
2. **The MuJoCo side**: :class:`RenderObserver` (``obs="render"`` in ``hydo/Bin-v0``), which renders
   the scene's cameras ``cam_front``, ``cam_left`` and ``cam_right`` at 240×320 and feeds the
   functions above; :func:`segmentation_iou` (depth-subtraction mask vs MuJoCo's segmentation of the
   object's geoms); :func:`render_rgb` (an oblique colour view with the goal ghost) and
   :func:`write_video`.

Offscreen rendering needs ``MUJOCO_GL=egl`` in the environment **before the first** ``import mujoco``
of the process (MuJoCo picks its OpenGL backend at import time; with it unset ``mujoco.Renderer``
fails: no display). This module sets it when it is unset; when mujoco was already imported without
it (``sim.env`` imports ``sim.scene`` first), it switches MuJoCo's renderer to the EGL backend itself.
"""

from __future__ import annotations

import os
import sys
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

_MUJOCO_IMPORTED_EARLIER = "mujoco" in sys.modules
os.environ.setdefault("MUJOCO_GL", "egl")

import cv2  # noqa: E402
import mujoco  # noqa: E402
import numpy as np  # noqa: E402
from scipy.spatial import cKDTree  # noqa: E402

from sim.observe import visible_surface  # noqa: E402
from sim.primitive import BIN_FLOOR_Z, BIN_INNER_SIZE_M  # noqa: E402


def _use_egl_if_asked() -> None:
    """Honour ``MUJOCO_GL=egl`` even when mujoco was imported before this module set it."""
    if not _MUJOCO_IMPORTED_EARLIER or os.environ.get("MUJOCO_GL", "").lower() != "egl":
        return
    from mujoco.rendering.classic import gl_context

    if getattr(gl_context, "_MUJOCO_GL", "egl") == "egl":  # mujoco already chose EGL itself
        return
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    from mujoco.egl import GLContext

    gl_context.GLContext = GLContext


_use_egl_if_asked()

CAMERAS = ("cam_front", "cam_left", "cam_right")
DEPTH_HEIGHT, DEPTH_WIDTH = 240, 320  # pixels; at 120x160 too few object pixels remain
OBJECT_THRESHOLD_M = 0.01  # a pixel closer than the background by more than this is foreground
MEDIAN_KSIZE = 5  # median filter (pixels) on the raw foreground mask
OPEN_KSIZE = 3  # morphological opening (pixels) after it
NORMAL_K = 16  # neighbours for PCA normals
BG_STRIDE = 4  # background pixels are taken on this pixel grid (every 4th row and column)
MAX_OBJECT_POINTS = 2048  # fused object points beyond this are randomly thinned (normals cost ~linear)
MIN_OBJECT_POINTS = 8  # fewer rendered object points than this: fall back to mesh samples
BIN_CROP_MARGIN_M = 0.01
#: Background points are kept inside this box (world frame, metres): the bin's inner volume + 1 cm
#: sideways, from 1 cm below the floor to 0.3 m above it.
BIN_CROP_LOW = np.array([*(-BIN_INNER_SIZE_M[:2] / 2 - BIN_CROP_MARGIN_M), BIN_FLOOR_Z - BIN_CROP_MARGIN_M])
BIN_CROP_HIGH = np.array([*(BIN_INNER_SIZE_M[:2] / 2 + BIN_CROP_MARGIN_M), BIN_FLOOR_Z + 0.3])
FAR_AWAY_POS = np.array([0.0, 0.0, 20.0])  # where the object goes for the background: above every view
#: A clutter body whose position (m) or quaternion component changed by more than this since the
#: last background render gets a new background (0.5 mm, or ~0.06 deg).
CLUTTER_MOVED = 5e-4
GHOST_GROUP = 4  # geom group of the goal ghost
MAX_CACHED_MODELS = 8  # renderers kept per observer (each holds an EGL context and mesh buffers)

# The RGB view: an oblique free camera looking into the bin from the front-left, above the rim.
RGB_LOOKAT = (0.0, 0.0, 0.03)  # metres
RGB_DISTANCE_M = 0.95
RGB_AZIMUTH_DEG = 150.0
RGB_ELEVATION_DEG = -42.0


# ==================================================================================================
# Pure image processing (no MuJoCo): shared with deploy
# ==================================================================================================


def pinhole_intrinsics(fovy_deg: float, width: int, height: int) -> np.ndarray:
    """Intrinsic matrix ``K`` (3, 3) float64 of an ideal pinhole camera with square pixels.

    ``fovy_deg`` is the full vertical field of view in degrees, ``width``/``height`` the image size
    in pixels. ``fx = fy = (height / 2) / tan(fovy / 2)``, principal point at the image centre
    ``((width - 1) / 2, (height - 1) / 2)`` in pixel-centre coordinates (MuJoCo's and OpenGL's).
    """
    f = 0.5 * height / np.tan(np.deg2rad(fovy_deg) / 2)
    return np.array([[f, 0.0, (width - 1) / 2], [0.0, f, (height - 1) / 2], [0.0, 0.0, 1.0]])


def valid_depth(depth: np.ndarray) -> np.ndarray:
    """Boolean mask (H, W) of usable depth pixels: finite and > 0 (0 and NaN are holes)."""
    d = np.asarray(depth)
    return np.isfinite(d) & (d > 0)


def backproject(
    depth: np.ndarray,
    K: np.ndarray,
    T_world_cam: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    stride: int = 1,
) -> np.ndarray:
    """Lift depth pixels to 3D points (P, 3) float32, metres.

    depth (H, W): z-depth in metres along the optical axis; NaN, inf and values <= 0 are holes and
    are skipped. K (3, 3): pinhole intrinsics. T_world_cam (4, 4): pose of the camera's **optical**
    frame (OpenCV: x right, y down, z forward) in the world; None keeps camera-frame points.
    mask (H, W) bool: only these pixels (and valid ones). stride: take every ``stride``-th row and
    column. Points come in row-major pixel order.
    """
    d = np.asarray(depth)[::stride, ::stride]
    keep = valid_depth(d)
    if mask is not None:
        keep &= np.asarray(mask, dtype=bool)[::stride, ::stride]
    v, u = np.nonzero(keep)
    z = d[v, u].astype(np.float64)
    v, u = v * stride, u * stride
    x = (u - K[0, 2]) * z / K[0, 0]
    y = (v - K[1, 2]) * z / K[1, 1]
    p = np.stack([x, y, z], axis=1)
    if T_world_cam is not None:
        p = p @ T_world_cam[:3, :3].T + T_world_cam[:3, 3]
    return p.astype(np.float32)


def background_from_frames(frames: np.ndarray) -> np.ndarray:
    """Background depth (H, W) float32 metres from empty-scene frames (K, H, W) or one frame (H, W).

    Per-pixel ``nanmedian`` with holes (0, NaN, inf) ignored: a plain median fails on sensor holes.
    Pixels that are holes in every frame stay NaN (unknown background).
    """
    f = np.array(frames, dtype=np.float32, copy=True)
    if f.ndim == 2:
        f = f[None]
    f[~valid_depth(f)] = np.nan
    if len(f) == 1:
        return f[0]
    all_nan = np.all(np.isnan(f), axis=0)
    f[:, all_nan] = 0.0  # keeps nanmedian quiet; restored to NaN below
    bg = np.nanmedian(f, axis=0).astype(np.float32)
    bg[all_nan] = np.nan
    return bg


def largest_component(mask: np.ndarray) -> np.ndarray:
    """The largest 8-connected component of a boolean mask (H, W) (empty stays empty)."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 2:  # background only, or a single component
        return mask.astype(bool)
    best = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    return labels == best


def subtract_background(
    depth: np.ndarray,
    background: np.ndarray,
    threshold_m: float = OBJECT_THRESHOLD_M,
    median_ksize: int = MEDIAN_KSIZE,
    open_ksize: int = OPEN_KSIZE,
    keep_largest: bool = True,
) -> np.ndarray:
    """Foreground (object) mask (H, W) bool of a depth image against an empty-scene background.

    depth (H, W), background (H, W): z-depth in metres (holes: 0, NaN, inf). A pixel is foreground
    when both are valid and ``background - depth > threshold_m`` (the object is nearer than what was
    there before); a hole in either image is never foreground. The raw mask is cleaned with a median
    filter (``median_ksize`` pixels, odd; 0 or 1 disables) and a morphological opening
    (``open_ksize``, elliptic; 0 or 1 disables), then reduced to its largest connected component
    when ``keep_largest`` (one target object in view).
    """
    d = np.asarray(depth, dtype=np.float32)
    bg = np.asarray(background, dtype=np.float32)
    if d.shape != bg.shape:
        raise ValueError(f"depth {d.shape} and background {bg.shape} must have the same shape")
    ok = valid_depth(d) & valid_depth(bg)
    with np.errstate(invalid="ignore"):
        raw = ok & (bg - d > threshold_m)
    m = raw.astype(np.uint8)
    if median_ksize > 1:
        m = cv2.medianBlur(m, median_ksize)
    if open_ksize > 1:
        kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (open_ksize, open_ksize))
        m = cv2.morphologyEx(m, cv2.MORPH_OPEN, kernel)
    mask = m.astype(bool) & ok
    return largest_component(mask) if keep_largest else mask


def _smallest_eigenvectors(C: np.ndarray) -> np.ndarray:
    """Unit eigenvectors (M, 3) of the smallest eigenvalue of symmetric matrices C (M, 3, 3).

    Closed form (trigonometric eigenvalues, then the largest cross product of two rows of
    ``C - λ_min I``): ~5x faster than ``np.linalg.eigh`` on many 3x3 matrices. An isotropic or
    degenerate C (no unique smallest direction) gives +z.
    """
    a00, a11, a22 = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    a01, a02, a12 = C[:, 0, 1], C[:, 0, 2], C[:, 1, 2]
    q = (a00 + a11 + a22) / 3
    p1 = a01**2 + a02**2 + a12**2
    p = np.sqrt(((a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2 * p1) / 6)
    ps = np.where(p > 0, p, 1.0)
    b00, b11, b22 = (a00 - q) / ps, (a11 - q) / ps, (a22 - q) / ps
    b01, b02, b12 = a01 / ps, a02 / ps, a12 / ps
    det_b = b00 * (b11 * b22 - b12**2) - b01 * (b01 * b22 - b12 * b02) + b02 * (b01 * b12 - b11 * b02)
    phi = np.arccos(np.clip(det_b / 2, -1.0, 1.0)) / 3
    lam = q + 2 * p * np.cos(phi + 2 * np.pi / 3)  # the smallest eigenvalue
    r0 = np.stack([a00 - lam, a01, a02], axis=1)
    r1 = np.stack([a01, a11 - lam, a12], axis=1)
    r2 = np.stack([a02, a12, a22 - lam], axis=1)
    cands = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)  # (M, 3, 3)
    norms = np.linalg.norm(cands, axis=2)
    best = np.argmax(norms, axis=1)
    rows = np.arange(len(C))
    v = cands[rows, best]
    nv = norms[rows, best]
    ok = nv > 1e-30
    out = np.zeros_like(v)
    out[:, 2] = 1.0
    out[ok] = v[ok] / nv[ok, None]
    return out


def estimate_normals(
    points: np.ndarray,
    k: int = NORMAL_K,
    viewpoints: np.ndarray | None = None,
) -> np.ndarray:
    """Unit surface normals (M, 3) float32 of a point cloud (M, 3) in metres.

    Each normal is the least-variance direction (PCA) of the point's ``k`` nearest neighbours
    (itself included; k is capped at M). Orientation: towards ``viewpoints`` (M, 3) or (3,) — the
    position of the camera that saw each point — when given, else away from the cloud's centroid.
    Fewer than 3 points: normals point from the centroid (or +z for a single point).
    """
    p = np.asarray(points, dtype=np.float64)
    m = len(p)
    if m == 0:
        return np.zeros((0, 3), dtype=np.float32)
    if m < 3:
        n = p - p.mean(axis=0)
        n[np.linalg.norm(n, axis=1) < 1e-12] = (0.0, 0.0, 1.0)
    else:
        _, idx = cKDTree(p).query(p, k=min(k, m))
        nb = p[idx]  # (M, k, 3)
        nb = nb - nb.mean(axis=1, keepdims=True)
        n = _smallest_eigenvectors(nb.transpose(0, 2, 1) @ nb)  # covariance (M, 3, 3)
    if viewpoints is not None:
        towards = np.broadcast_to(np.asarray(viewpoints, dtype=np.float64), p.shape) - p
    else:
        towards = p - p.mean(axis=0)
    flip = (n * towards).sum(axis=1) < 0
    n[flip] = -n[flip]
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return n.astype(np.float32)


def crop_box(points: np.ndarray, low, high) -> np.ndarray:
    """Points (P, 3) inside the axis-aligned box ``[low, high]`` (3,) each, metres."""
    keep = np.all((points >= np.asarray(low)) & (points <= np.asarray(high)), axis=1)
    return points[keep]


def mask_iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union of two boolean masks of one shape; 1.0 when both are empty."""
    a, b = np.asarray(a, dtype=bool), np.asarray(b, dtype=bool)
    union = np.count_nonzero(a | b)
    return 1.0 if union == 0 else np.count_nonzero(a & b) / union


def clouds_from_depth(
    depths: list[np.ndarray],
    backgrounds: list[np.ndarray],
    Ks: list[np.ndarray],
    T_world_cams: list[np.ndarray],
    rng: np.random.Generator,
    crop_low=None,
    crop_high=None,
    bg_stride: int = BG_STRIDE,
    max_object_points: int = MAX_OBJECT_POINTS,
    keep_largest: bool = True,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[np.ndarray]]:
    """Fuse several depth cameras into segmented clouds: the whole per-frame pipeline.

    Per camera: ``depths[i]`` (H, W) metres against ``backgrounds[i]`` (H, W) metres (holes: 0/NaN),
    intrinsics ``Ks[i]`` (3, 3), optical-frame pose ``T_world_cams[i]`` (4, 4). Returns
    ``(obj_points (M, 3), obj_normals (M, 3), bg_points (L, 3), masks)`` float32, world frame,
    metres, and the per-camera object masks (H, W) bool. Object points: all masked pixels of all
    cameras, randomly thinned (``rng``) to ``max_object_points``; normals by :func:`estimate_normals`
    oriented towards the camera that saw each point. Background points: unmasked valid pixels,
    excluding raw foreground and a 2-pixel rim around the mask, on a ``bg_stride`` pixel grid,
    inside the box ``crop_low``..``crop_high`` (default: the bin, ``BIN_CROP_LOW``/``BIN_CROP_HIGH``).
    M may be 0 (nothing segmented): the caller decides what that means.
    """
    crop_low = BIN_CROP_LOW if crop_low is None else crop_low
    crop_high = BIN_CROP_HIGH if crop_high is None else crop_high
    rim = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    obj, views, bg, masks = [], [], [], []
    for depth, background, K, T in zip(depths, backgrounds, Ks, T_world_cams, strict=True):
        mask = subtract_background(depth, background, keep_largest=keep_largest)
        masks.append(mask)
        p = backproject(depth, K, T, mask)
        obj.append(p)
        views.append(np.broadcast_to(np.asarray(T, dtype=np.float32)[:3, 3], p.shape))
        with np.errstate(invalid="ignore"):
            near = (background - depth > OBJECT_THRESHOLD_M) | cv2.dilate(mask.astype(np.uint8), rim).astype(
                bool
            )
        bg.append(crop_box(backproject(depth, K, T, ~near, stride=bg_stride), crop_low, crop_high))
    obj_p, views, bg_p = np.concatenate(obj), np.concatenate(views), np.concatenate(bg)
    if len(obj_p) > max_object_points:
        keep = np.sort(rng.choice(len(obj_p), max_object_points, replace=False))
        obj_p, views = obj_p[keep], views[keep]
    return obj_p, estimate_normals(obj_p, NORMAL_K, views), bg_p, masks


# ==================================================================================================
# MuJoCo side
# ==================================================================================================

# MuJoCo cameras look along -z with y up; OpenCV's optical frame looks along +z with y down.
_GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def camera_pose_cv(data: mujoco.MjData, cam_id: int) -> np.ndarray:
    """Pose (4, 4) of camera ``cam_id``'s OpenCV optical frame in the world (after mj_forward)."""
    T = np.eye(4)
    T[:3, :3] = data.cam_xmat[cam_id].reshape(3, 3) @ _GL_TO_CV
    T[:3, 3] = data.cam_xpos[cam_id]
    return T


class _RendererPool:
    """``mujoco.Renderer`` objects keyed by model (LRU, closed on eviction), one size each."""

    def __init__(self, max_models: int):
        self.max_models = max_models
        self._items: OrderedDict[int, tuple[mujoco.MjModel, mujoco.Renderer, dict]] = OrderedDict()

    def get(self, model: mujoco.MjModel, height: int, width: int) -> tuple[mujoco.Renderer, dict]:
        """The renderer for ``model`` at ``height`` x ``width`` and a per-model scratch dict."""
        key = id(model)
        item = self._items.get(key)
        if item is not None and (item[0] is not model or (item[1].height, item[1].width) != (height, width)):
            item[1].close()  # a recycled id or another size: start over
            del self._items[key]
            item = None
        if item is None:
            while len(self._items) >= self.max_models:
                _, (_, old, _) = self._items.popitem(last=False)
                old.close()
            item = (model, mujoco.Renderer(model, height, width), {})
            self._items[key] = item
        self._items.move_to_end(key)
        return item[1], item[2]

    def close(self) -> None:
        for _, r, _ in self._items.values():
            r.close()
        self._items.clear()


def _depth_option() -> mujoco.MjvOption:
    """Depth cameras draw geom groups 0-1 only: the bin, the object and clutter.

    Off: the goal ghost (4), the hand's collision boxes (3) and group 2, i.e. the parked hand's
    visual meshes (outside every view when observations are taken) and the ground plane around the
    bin (outside the bin crop; a pixel that sees nothing reads the far plane, in the background and
    in the frame alike, so it is never foreground). Drawing group 2 doubles the render time.
    """
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 0
    opt.geomgroup[:2] = 1
    opt.sitegroup[:] = 0
    return opt


@dataclass
class CameraFrames:
    """One rendered view set of a scene, per camera (the inputs of :func:`clouds_from_depth`)."""

    depth: list[np.ndarray]  # (H, W) float32 metres each, noise included
    background: list[np.ndarray]  # (H, W) float32 metres each (target object removed)
    T_world_cam: list[np.ndarray]  # (4, 4) optical-frame poses
    K: list[np.ndarray]  # (3, 3) intrinsics


class RenderObserver:
    """Segmented clouds from three rendered depth cameras and depth background subtraction.

    ``segmented_clouds(scene) -> (obj_points (M, 3), obj_normals (M, 3), bg_points (L, 3))``, world
    frame, float32 metres, like :class:`sim.observe.MeshObserver`. Per camera: render depth (geom
    groups 0-1: bin, object, clutter; the hand is parked and the goal ghost hidden), add Gaussian
    noise of ``noise`` metres, subtract the background (the same scene with the target object
    removed, rendered once per model and clutter layout), back-project the mask; then fuse the three
    views (randomly thinned to ``MAX_OBJECT_POINTS``) and estimate PCA normals oriented towards the
    seeing camera. Background points are the unmasked pixels (minus a 2-pixel rim around the mask)
    on a ``BG_STRIDE`` grid inside ``BIN_CROP_LOW``..``BIN_CROP_HIGH``.

    When fewer than ``MIN_OBJECT_POINTS`` object pixels are seen (object out of view or hidden),
    the object points fall back to the visible mesh samples and ``self.fallbacks`` counts it.
    The noise generator is the observer's own (``seed``), so the env's random stream is untouched.
    """

    name = "render"

    def __init__(
        self,
        noise: float = 0.0,
        cameras: tuple[str, ...] = CAMERAS,
        height: int = DEPTH_HEIGHT,
        width: int = DEPTH_WIDTH,
        seed: int | None = None,
        max_models: int = MAX_CACHED_MODELS,
    ):
        if noise < 0:
            raise ValueError(f"`noise` must be >= 0 metres. Got {noise!r}.")
        self.noise = float(noise)
        self.cameras = tuple(cameras)
        self.height, self.width = height, width
        self.rng = np.random.default_rng(seed)
        self.fallbacks = 0
        self._pool = _RendererPool(max_models)
        self._option = _depth_option()

    def close(self) -> None:
        self._pool.close()

    # --- rendering -------------------------------------------------------------------------------
    def _renderer(self, scene):
        r, cache = self._pool.get(scene.model, self.height, self.width)
        if not cache:
            m = scene.model
            cache["cam_ids"] = [m.camera(c).id for c in self.cameras]
            cache["K"] = [
                pinhole_intrinsics(m.cam_fovy[i], self.width, self.height) for i in cache["cam_ids"]
            ]
            cache["scratch"] = mujoco.MjData(m)
        return r, cache

    def _render_depths(self, r: mujoco.Renderer, data: mujoco.MjData, cam_ids) -> list[np.ndarray]:
        r.enable_depth_rendering()
        out = []
        for c in cam_ids:
            r.update_scene(data, c, self._option)
            out.append(r.render())
        return out

    def _backgrounds(self, scene, r, cache) -> list[np.ndarray]:
        """Depth (H, W) per camera of the scene without the target object.

        Rendered once per model, and again whenever a clutter body has moved by more than
        ``CLUTTER_MOVED`` since the last background (clutter belongs to the background).
        """
        layout = np.array(
            [np.concatenate(scene.object_pose(f"clutter{i}")) for i in range(len(scene.clutter))]
        )
        old = cache.get("bg_layout")
        if old is None or np.abs(layout - old).max(initial=0.0) > CLUTTER_MOVED:
            d = cache["scratch"]
            d.qpos[:] = scene.data.qpos
            d.mocap_pos[:] = scene.data.mocap_pos
            d.mocap_quat[:] = scene.data.mocap_quat
            d.qpos[scene.obj_qadr : scene.obj_qadr + 3] = FAR_AWAY_POS
            mujoco.mj_kinematics(scene.model, d)
            mujoco.mj_comPos(scene.model, d)
            mujoco.mj_camlight(scene.model, d)
            cache["bg"] = [background_from_frames(x) for x in self._render_depths(r, d, cache["cam_ids"])]
            cache["bg_layout"] = layout
        return cache["bg"]

    def frames(self, scene) -> CameraFrames:
        """Render every camera of ``scene``: depth (noise added), background, pose and K."""
        r, cache = self._renderer(scene)
        backgrounds = self._backgrounds(scene, r, cache)
        depths = self._render_depths(r, scene.data, cache["cam_ids"])
        if self.noise > 0:
            depths = [d + self.noise * self.rng.standard_normal(d.shape, dtype=np.float32) for d in depths]
        poses = [camera_pose_cv(scene.data, c) for c in cache["cam_ids"]]
        return CameraFrames(depths, backgrounds, poses, list(cache["K"]))

    def true_masks(self, scene) -> list[np.ndarray]:
        """Ground truth (H, W) bool per camera: pixels where MuJoCo's segmentation shows the object."""
        r, cache = self._renderer(scene)
        geoms = np.flatnonzero(scene.model.geom_bodyid == scene.obj_body)
        r.enable_segmentation_rendering()
        out = []
        for c in cache["cam_ids"]:
            r.update_scene(scene.data, c, self._option)
            seg = r.render()
            out.append((seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], geoms))
        r.disable_segmentation_rendering()
        return out

    # --- the observer interface -------------------------------------------------------------------
    def segmented_clouds(self, scene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(obj_points (M, 3), obj_normals (M, 3), bg_points (L, 3))`` world frame, float32 metres."""
        f = self.frames(scene)
        obj_p, obj_n, bg_p, _ = clouds_from_depth(f.depth, f.background, f.K, f.T_world_cam, self.rng)
        if len(obj_p) < MIN_OBJECT_POINTS:
            self.fallbacks += 1
            obj_p, obj_n = visible_surface(
                scene.asset.surface_points, scene.asset.surface_normals, scene.object_T()
            )
            obj_p, obj_n = obj_p.astype(np.float32), obj_n.astype(np.float32)
        if len(bg_p) == 0:  # the bin out of every view: cannot happen with the shipped cameras
            raise RuntimeError("no background pixel inside the bin box: check the camera poses")
        return obj_p, obj_n, bg_p

    def segmentation_iou(self, scene) -> float:
        """IoU of the depth-subtraction masks vs MuJoCo's segmentation, pooled over all cameras."""
        f = self.frames(scene)
        pred = np.stack([subtract_background(d, bg) for d, bg in zip(f.depth, f.background, strict=True)])
        true = np.stack(self.true_masks(scene))
        return mask_iou(pred, true)


def segmentation_iou(scene, observer: RenderObserver | None = None) -> float:
    """IoU (pooled over the three cameras) of the background-subtraction object mask vs MuJoCo's
    segmentation render of the object's geoms (ground truth) for a :class:`sim.scene.BinScene`.

    Pass the ``observer`` in use to reuse its renderers (and its depth noise); a throwaway noise-free
    one is made otherwise.
    """
    if observer is not None:
        return observer.segmentation_iou(scene)
    obs = RenderObserver()
    try:
        return obs.segmentation_iou(scene)
    finally:
        obs.close()


# --- RGB frames and videos --------------------------------------------------------------------------


def _rgb_option(model: mujoco.MjModel) -> mujoco.MjvOption:
    opt = mujoco.MjvOption()
    opt.geomgroup[:] = 0
    opt.geomgroup[[0, 1, 2, GHOST_GROUP]] = 1  # scene, hand visual meshes, goal ghost (translucent)
    hand = model.body("hand").id
    if not np.any((model.geom_bodyid == hand) & (model.geom_group == 2)):
        opt.geomgroup[3] = 1  # no Panda meshes installed: show the hand's collision boxes instead
    return opt


def rgb_camera() -> mujoco.MjvCamera:
    """The fixed oblique free camera of :func:`render_rgb`."""
    cam = mujoco.MjvCamera()
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = RGB_LOOKAT
    cam.distance = RGB_DISTANCE_M
    cam.azimuth = RGB_AZIMUTH_DEG
    cam.elevation = RGB_ELEVATION_DEG
    return cam


def render_rgb(env, width: int = 320, height: int = 240) -> np.ndarray:
    """A colour frame (height, width, 3) uint8 of ``env``'s current scene (a ``BinEnv``, reset).

    Fixed oblique viewpoint, goal ghost shown, hand visual meshes shown. The renderers are cached on
    ``env._renderer`` (closed by ``env.close()``).
    """
    env = getattr(env, "unwrapped", env)
    scene = getattr(env, "scene", None)
    if scene is None:
        raise RuntimeError("call reset() before render_rgb()")
    if not isinstance(env._renderer, _RendererPool):
        env._renderer = _RendererPool(max_models=4)
    if width > scene.model.vis.global_.offwidth or height > scene.model.vis.global_.offheight:
        raise ValueError(
            f"render_rgb size {width}x{height} exceeds the scene's offscreen buffer "
            f"{scene.model.vis.global_.offwidth}x{scene.model.vis.global_.offheight}"
        )
    r, cache = env._renderer.get(scene.model, height, width)
    if "option" not in cache:
        cache["option"] = _rgb_option(scene.model)
        cache["camera"] = rgb_camera()
    r.disable_depth_rendering()
    r.disable_segmentation_rendering()
    r.update_scene(scene.data, cache["camera"], cache["option"])
    return r.render()


def write_video(frames, path: str | os.PathLike, fps: float) -> Path:
    """Write RGB frames (each (H, W, 3) uint8, one size) to ``path`` as an mp4v video; returns path.

    Written to a temporary file next to ``path`` and moved into place with ``os.replace``, so
    ``path`` is never half-written. Raises ``ValueError`` on no frames, mixed sizes or a writer that
    cannot open (unwritable folder, an extension OpenCV has no container for).
    """
    frames = list(frames)
    if not frames:
        raise ValueError(f"no frames to write to {path}")
    if fps <= 0:
        raise ValueError(f"`fps` must be > 0. Got {fps!r}.")
    h, w = frames[0].shape[:2]
    for i, f in enumerate(frames):
        if f.shape != (h, w, 3) or f.dtype != np.uint8:
            raise ValueError(f"frame {i} is {f.shape} {f.dtype}, expected ({h}, {w}, 3) uint8")
    path = Path(path)
    tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp{path.suffix}")
    writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), float(fps), (w, h))
    try:
        if not writer.isOpened():
            raise ValueError(
                f"cannot open a video writer for {path} (fourcc mp4v, {w}x{h}): "
                "check that the folder exists and is writable and the suffix is .mp4"
            )
        for f in frames:
            writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
        writer.release()
        os.replace(tmp, path)
    except BaseException:
        writer.release()
        tmp.unlink(missing_ok=True)
        raise
    return path
