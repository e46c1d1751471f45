"""Writing RGB frames to a video file (OpenCV, no MuJoCo): :func:`write_video`.

The frames come from ``sim.render.render_rgb`` (evaluation videos) or anywhere else.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np


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
