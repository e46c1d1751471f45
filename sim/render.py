"""The MuJoCo renderer: rendered depth observations (three depth cameras) and RGB frames.

- :class:`RenderObserver` (``obs="render"`` in ``hydo/Bin-v0``) renders the scene's cameras
  ``cam_front``, ``cam_left`` and ``cam_right`` at 240×320 and turns them into segmented clouds with
  the pure depth pipeline of ``sim.depth`` (background subtraction, back-projection, normals: the
  same functions deploy runs on real frames); :func:`segmentation_iou` compares its depth-subtraction
  mask with MuJoCo's segmentation of the object's geoms.
- :func:`render_rgb` renders an oblique colour view with the goal ghost (``sim.video.write_video``
  writes such frames to a file).

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

_MUJOCO_IMPORTED_EARLIER = "mujoco" in sys.modules
os.environ.setdefault("MUJOCO_GL", "egl")

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from sim.depth import (  # noqa: E402
    background_from_frames,
    clouds_from_depth,
    mask_iou,
    pinhole_intrinsics,
    subtract_background,
)
from sim.observe import CAMERAS, DEPTH_HEIGHT, DEPTH_WIDTH, camera_pose_cv, visible_surface  # noqa: E402, F401


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

MIN_OBJECT_POINTS = 8  # fewer rendered object points than this: fall back to mesh samples
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
    on a ``BG_STRIDE`` grid inside ``BIN_CROP_LOW``..``BIN_CROP_HIGH`` (constants of ``sim.depth``).

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
