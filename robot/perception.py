"""Perception: depth frames → segmented object and background clouds in the robot base frame.

Per step (``segment``): check every depth image (finite, the background's shape; zeros are holes,
NaN/inf are refused naming the camera), check the background still matches (a bumped camera is
refused: re-capture the background), then ``sim.depth.clouds_from_depth`` — the same background
subtraction, back-projection, fusion and PCA normals as the training renderer — with each camera's
cell intrinsics and extrinsics, background points cropped to the bin box, object points cropped to
the bin's volume. Too few object points is refused (empty or tiny mask). ``observation`` resamples
the clouds to the policy's fixed point counts with ``sim.contract.build_observation``.

The empty-bin background (``capture_background``, ``hydo deploy capture-background``) is the
per-pixel ``nanmedian`` of several frames (holes ignored), taken with the arm at its home pose.
"""

from __future__ import annotations

import hashlib
import json
import time
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from robot.errors import PerceptionError
from sim.contract import build_observation
from sim.depth import background_from_frames, clouds_from_depth, valid_depth

BIN_MARGIN_M = 0.01  # background crop: the bin's inner box grown by this (walls' inner faces kept)
OBJECT_HEIGHT_MAX_M = 0.30  # object points above the floor by more than this are not the object
MISMATCH_THRESHOLD_M = 0.02  # a non-object pixel this far from the background counts as moved
MISMATCH_RIM_PX = 7  # pixels around the object mask not counted (shadows, mixed pixels)


@dataclass
class Background:
    """Empty-bin depth per camera, with the calibration it was captured under."""

    depth: dict[str, np.ndarray]  # serial -> (H, W) float32 metres, NaN where unknown
    calibration: str  # hash of the cameras' intrinsics and extrinsics at capture time
    captured_at: float  # time.time()

    def save(self, path: str | Path) -> Path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp.npz")
        np.savez_compressed(
            tmp,
            **{f"depth/{s}": d for s, d in self.depth.items()},
            meta=np.array(json.dumps({"calibration": self.calibration, "captured_at": self.captured_at})),
        )
        tmp.replace(path)
        return path

    @classmethod
    def load(cls, path: str | Path, cell) -> Background:
        """Read a ``capture-background`` file and check it is of ``cell``'s cameras; anything else
        (missing, zero bytes, truncated, not an .npz, wrong keys, types or shapes) is one
        ``PerceptionError`` line naming the file."""
        path = Path(path)
        if not path.is_file():
            raise PerceptionError(
                f"background {path} does not exist: run `hydo deploy capture-background --cell {cell.source}` "
                "with the bin empty and the arm at home"
            )
        again = f"capture it again (`hydo deploy capture-background --cell {cell.source}`)"
        arrays = read_npz(path, "background", PerceptionError, again)
        meta = read_meta(arrays, path, "background", PerceptionError, again)

        def bad(what: str) -> PerceptionError:
            return PerceptionError(f"background {path}: {what}: {again}")

        depth = {}
        for k, a in arrays.items():
            if not k.startswith("depth/"):
                continue
            if a.ndim != 2 or a.dtype.kind != "f":
                raise bad(f"`{k}` must be a 2D float depth image, got {a.dtype} of shape {a.shape}")
            depth[k.removeprefix("depth/")] = a.astype(np.float32)
        if not depth:
            raise bad("no `depth/<serial>` images")
        calibration, captured_at = meta.get("calibration"), meta.get("captured_at", 0.0)
        if not isinstance(calibration, str):
            raise bad(f"`meta.calibration` must be a string, got {calibration!r}")
        if isinstance(captured_at, bool) or not isinstance(captured_at, int | float):
            raise bad(f"`meta.captured_at` must be a number, got {captured_at!r}")
        bg = cls(depth, calibration, float(captured_at))
        bg.check(cell, f"background {path}")
        return bg

    def check(self, cell, source: str = "background") -> None:
        """Refuse a background of other cameras, sizes or calibration than ``cell``'s."""
        for cam in cell.cameras:
            d = self.depth.get(cam.serial)
            if d is None:
                raise PerceptionError(
                    f"{source} has no frame of camera {cam.label}: capture the background again"
                )
            if d.shape != (cam.height, cam.width):
                raise PerceptionError(
                    f"{source}: camera {cam.label} frame is {d.shape}, the cell says {(cam.height, cam.width)}"
                )
        if self.calibration != calibration_hash(cell):
            raise PerceptionError(
                f"{source} was captured under another camera calibration: run `hydo deploy capture-background` again"
            )


def read_npz(path: Path, what: str, error: type[Exception], fix: str) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path``, read now (so a truncated member fails here, not later).

    The one reader of deploy's captures (background, goal): numpy reports a damaged file as
    ``EOFError``, ``zipfile.BadZipFile``, ``zlib.error``, ``ValueError`` (pickled or random data) or
    ``OSError``; each becomes one ``error`` line naming the file. Pickles are never loaded.
    """
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a bare .npy array, not an archive
            raise error(f"{what} {path} is a single .npy array, not an .npz archive: {fix}")
        with z:
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        reason = "empty file (0 bytes)" if path.stat().st_size == 0 else "truncated or not an .npz archive"
        # numpy's ValueError on random bytes is about pickles, which would only mislead here
        first = "" if isinstance(e, ValueError) else (str(e).strip().splitlines() or [""])[0][:100]
        detail = f"{e.__class__.__name__}: {first}" if first else e.__class__.__name__
        raise error(f"{what} {path} is unreadable, {reason} ({detail}): {fix}") from None


def read_meta(arrays: dict, path: Path, what: str, error: type[Exception], fix: str) -> dict:
    """The JSON object stored as the 0-d string array ``meta`` of a capture."""
    m = arrays.get("meta")
    if m is None or m.shape != () or m.dtype.kind != "U":
        raise error(f"{what} {path}: no `meta` string (not a hydo capture?): {fix}")
    try:
        meta = json.loads(str(m))
    except json.JSONDecodeError:
        raise error(f"{what} {path}: `meta` is not valid JSON: {fix}") from None
    if not isinstance(meta, dict):
        raise error(f"{what} {path}: `meta` must be a JSON object, got {type(meta).__name__}: {fix}")
    return meta


def calibration_hash(cell) -> str:
    h = hashlib.sha256()
    for cam in cell.cameras:
        h.update(cam.serial.encode())
        h.update(np.round(cam.K, 6).tobytes())
        h.update(np.round(cam.T_base_camera, 6).tobytes())
    return h.hexdigest()[:16]


def check_depth(frame, spec) -> None:
    """Refuse NaN/inf pixels or a wrong size (zeros are holes, not errors)."""
    d = np.asarray(frame.depth)
    if d.shape != (spec.height, spec.width):
        raise PerceptionError(
            f"camera {spec.label}: depth frame is {d.shape}, the cell says {(spec.height, spec.width)}"
        )
    if not np.all(np.isfinite(d)):
        bad = int(np.count_nonzero(~np.isfinite(d)))
        raise PerceptionError(
            f"camera {spec.label}: depth tensor has {bad} NaN/inf pixels: refusing the frame"
        )
    if np.any(d < 0):
        raise PerceptionError(f"camera {spec.label}: depth tensor has negative values: refusing the frame")


def capture_background(cameras, cell, n_frames: int | None = None) -> Background:
    """Per-pixel nanmedian of ``n_frames`` frames of every camera (empty bin, arm at home)."""
    n = cell.perception.background_frames if n_frames is None else n_frames
    stacks: dict[str, list[np.ndarray]] = {c.serial: [] for c in cameras}
    for _ in range(n):
        for cam in cameras:
            f = cam.capture()
            check_depth(f, cam.spec)
            stacks[cam.serial].append(f.depth)
    depth = {s: background_from_frames(np.stack(v)) for s, v in stacks.items()}
    for cam in cameras:
        if np.count_nonzero(np.isfinite(depth[cam.serial])) < 0.5 * depth[cam.serial].size:
            raise PerceptionError(
                f"camera {cam.spec.label}: more than half of the background is holes: check the camera's view"
            )
    return Background(depth, calibration_hash(cell), time.time())


@dataclass
class Segmented:
    """One step's perception output (world = robot base frame, metres)."""

    obj_points: np.ndarray  # (M, 3) float32
    obj_normals: np.ndarray  # (M, 3) float32, towards the camera that saw each point
    bg_points: np.ndarray  # (L, 3) float32
    masks: list[np.ndarray]  # per camera (H, W) bool object mask
    mismatch: list[float]  # per camera fraction of bin pixels that moved away from the background


def background_mismatch(depth: np.ndarray, background: np.ndarray, mask: np.ndarray) -> float:
    """Fraction of valid pixels (outside the object and its rim) further than 2 cm from the background."""
    ok = valid_depth(depth) & valid_depth(background)
    rim = cv2.dilate(mask.astype(np.uint8), np.ones((2 * MISMATCH_RIM_PX + 1,) * 2, np.uint8)).astype(bool)
    ok &= ~rim
    n = np.count_nonzero(ok)
    if n == 0:
        return 1.0
    with np.errstate(invalid="ignore"):
        moved = np.abs(depth - background) > MISMATCH_THRESHOLD_M
    return float(np.count_nonzero(moved & ok)) / n


def segment(frames, background: Background, cell, rng: np.random.Generator) -> Segmented:
    """Frames (one per cell camera, cell order) → :class:`Segmented`; raises ``PerceptionError``."""
    if len(frames) != len(cell.cameras):
        raise PerceptionError(f"expected {len(cell.cameras)} frames (one per camera), got {len(frames)}")
    depths, bgs = [], []
    for f, cam in zip(frames, cell.cameras, strict=True):
        if f.serial != cam.serial:
            raise PerceptionError(f"frame from camera {f.serial} where {cam.label} was expected")
        check_depth(f, cam)
        depths.append(np.asarray(f.depth, dtype=np.float32))
        bgs.append(background.depth[cam.serial])
    lo = cell.bin_low - [BIN_MARGIN_M, BIN_MARGIN_M, BIN_MARGIN_M]
    hi = cell.bin_high + [BIN_MARGIN_M, BIN_MARGIN_M, 0.0]
    hi[2] = cell.floor_z + OBJECT_HEIGHT_MAX_M
    obj_p, obj_n, bg_p, masks = clouds_from_depth(
        depths,
        bgs,
        [c.K for c in cell.cameras],
        [c.T_base_camera for c in cell.cameras],
        rng,
        crop_low=lo,
        crop_high=hi,
    )
    mismatch = [background_mismatch(d, b, m) for d, b, m in zip(depths, bgs, masks, strict=True)]
    for frac, cam in zip(mismatch, cell.cameras, strict=True):
        if frac > cell.perception.max_background_mismatch:
            raise PerceptionError(
                f"camera {cam.label}: {frac:.0%} of the view no longer matches the background (camera moved, "
                "or something new in the bin): run `hydo deploy capture-background` again"
            )
    inside = np.all((obj_p >= lo) & (obj_p <= hi), axis=1)
    obj_p, obj_n = obj_p[inside], obj_n[inside]
    if len(obj_p) < cell.perception.min_object_points:
        pixels = [int(m.sum()) for m in masks]
        raise PerceptionError(
            f"object segmentation is empty or tiny: {len(obj_p)} object points inside the bin "
            f"(minimum {cell.perception.min_object_points}; mask pixels per camera {pixels})"
        )
    if len(bg_p) == 0:
        raise PerceptionError("no background point inside the bin: check the cameras' extrinsics")
    if not (np.all(np.isfinite(obj_n)) and np.all(np.isfinite(obj_p))):
        raise PerceptionError("object tensor `normals` or `points` contains NaN/inf: refusing the frame")
    return Segmented(obj_p, obj_n, bg_p, masks, mismatch)


def observation(seg: Segmented, T_rel: np.ndarray, n_obj: int, n_bg: int, rng: np.random.Generator):
    """The policy's observation: ``build_observation`` with goal flow ``T_rel·p − p``.

    ``T_rel`` (4, 4) maps the current object points onto the goal (registration); passing it as
    ``T_goal`` with ``T_obj = I`` gives exactly training's ``T_goal·T_obj⁻¹·p − p``.
    """
    return build_observation(
        seg.obj_points, seg.obj_normals, seg.bg_points, np.eye(4), T_rel, n_obj, n_bg, rng
    )
