"""Depth cameras behind one interface: Intel RealSense, the twin's rendered cameras, session replay.

This module holds the interface, the RealSense and the replay camera; the twin's camera is
``robot.twin.TwinCamera``, and ``robot.connect.open_cameras`` picks the cameras for ``--robot``.

Every camera yields :class:`Frame` objects: a depth image in metres (0 = hole, as a RealSense
reports it; NaN/inf are refused by perception), the capture time on the host clock and a counter.
The camera's serial, intrinsics and extrinsics come from the cell (``robot.cell.CameraSpec``), never
from the device, so calibration lives in one file.

``RealSenseCamera`` imports ``pyrealsense2`` lazily and follows robot-safety.md's RealSense rules:
one pipeline per serial, depth aligned to colour, a USB 3 check at start-up, the first frames
dropped (auto-exposure), ``try_wait_for_frames`` with one hardware reset and one retry on a timeout,
and every pipeline stopped in ``finally`` (a crash must not leave the device busy).
"""

from __future__ import annotations

import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot.errors import CameraError

FRAME_TIMEOUT_S = 2.0  # per try_wait_for_frames


class ReplayExhausted(CameraError):
    """A replay camera has played every recorded frame: the replay ends (not a failure)."""


@dataclass
class Frame:
    """One depth image from one camera."""

    serial: str
    depth: np.ndarray  # (H, W) float32 metres, z-depth in the optical frame; 0 = hole
    timestamp: float  # host clock (time.time()), seconds
    index: int  # frame counter of this camera


class Camera(ABC):
    """A depth camera: ``open`` → ``capture`` ... → ``close`` (also a context manager)."""

    kind = "camera"

    def __init__(self, spec):
        self.spec = spec  # robot.cell.CameraSpec

    @property
    def serial(self) -> str:
        return self.spec.serial

    @abstractmethod
    def open(self) -> None:
        """Start streaming; raise ``CameraError`` naming the camera if it cannot."""

    @abstractmethod
    def close(self) -> None: ...

    @abstractmethod
    def capture(self) -> Frame:
        """The next frame; raise ``CameraError`` naming the camera on a timeout it cannot recover."""

    def __enter__(self) -> Camera:
        self.open()
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


class CameraSet:
    """Several cameras opened together and always closed together (even when one fails to open)."""

    def __init__(self, cameras: list[Camera]):
        self.cameras = list(cameras)
        self._opened: list[Camera] = []

    def __enter__(self) -> CameraSet:
        try:
            for cam in self.cameras:
                cam.open()
                self._opened.append(cam)
        except BaseException:
            self.close()
            raise
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False

    def close(self) -> None:
        errors = []
        while self._opened:
            cam = self._opened.pop()
            try:
                cam.close()
            except Exception as e:  # close every pipeline, report the first failure afterwards
                errors.append(f"{cam.spec.label}: {e}")
        if errors:
            raise CameraError(f"could not stop camera pipelines: {'; '.join(errors)}")

    def capture(self) -> list[Frame]:
        return [cam.capture() for cam in self.cameras]

    def __iter__(self):
        return iter(self.cameras)

    def __len__(self) -> int:
        return len(self.cameras)


# --- Intel RealSense --------------------------------------------------------------------------------


def _import_realsense():
    try:
        import pyrealsense2 as rs
    except ImportError as e:
        raise CameraError(
            f"pyrealsense2 is not installed or cannot load ({e}): `pip install pyrealsense2==2.59.1.11053` "
            "(Debian also needs `apt-get install libusb-1.0-0`)"
        ) from None
    return rs


class RealSenseCamera(Camera):
    """One Intel RealSense D400 by serial: aligned depth (metres) at the cell's resolution and fps."""

    kind = "realsense"

    def __init__(self, spec, warmup_frames: int = 5, timeout_s: float = FRAME_TIMEOUT_S):
        super().__init__(spec)
        self.warmup_frames = warmup_frames
        self.timeout_ms = int(timeout_s * 1000)
        self._rs = None
        self._pipeline = None
        self._align = None
        self._scale = 0.001
        self._count = 0

    def _start(self) -> None:
        rs = self._rs
        cfg = rs.config()
        cfg.enable_device(self.spec.serial)
        cfg.enable_stream(rs.stream.depth, self.spec.width, self.spec.height, rs.format.z16, self.spec.fps)
        cfg.enable_stream(rs.stream.color, self.spec.width, self.spec.height, rs.format.rgb8, self.spec.fps)
        self._pipeline = rs.pipeline()
        profile = self._pipeline.start(cfg)
        self._scale = float(profile.get_device().first_depth_sensor().get_depth_scale())
        self._align = rs.align(rs.stream.color)
        for _ in range(self.warmup_frames):  # auto-exposure warm-up
            self._pipeline.try_wait_for_frames(self.timeout_ms)

    def open(self) -> None:
        rs = self._rs = _import_realsense()
        devices = {d.get_info(rs.camera_info.serial_number): d for d in rs.context().query_devices()}
        if self.spec.serial not in devices:
            raise CameraError(
                f"camera {self.spec.label} is not connected (connected serials: {sorted(devices) or 'none'}); "
                "check the cable and the serial in the cell file"
            )
        dev = devices[self.spec.serial]
        usb = (
            dev.get_info(rs.camera_info.usb_type_descriptor)
            if dev.supports(rs.camera_info.usb_type_descriptor)
            else ""
        )
        if usb and not usb.startswith("3"):
            raise CameraError(
                f"camera {self.spec.label} is on a USB {usb} link: depth at {self.spec.width}x{self.spec.height} "
                "needs USB 3; plug it into a USB 3 port with a USB 3 cable"
            )
        try:
            self._start()
        except RuntimeError as e:
            self.close()
            raise CameraError(f"camera {self.spec.label} cannot start streaming: {e}") from None

    def _wait(self):
        ok, frames = self._pipeline.try_wait_for_frames(self.timeout_ms)
        return frames if ok else None

    def capture(self) -> Frame:
        if self._pipeline is None:
            raise CameraError(f"camera {self.spec.label} is not open")
        frames = self._wait()
        if frames is None:  # one hardware reset and one retry, then give up naming the camera
            try:
                self._pipeline.stop()
                dev = next(
                    d
                    for d in self._rs.context().query_devices()
                    if d.get_info(self._rs.camera_info.serial_number) == self.spec.serial
                )
                dev.hardware_reset()
                time.sleep(2.0)
                self._start()
                frames = self._wait()
            except (RuntimeError, StopIteration):
                frames = None
            if frames is None:
                raise CameraError(
                    f"camera {self.spec.label} timed out twice (one hardware reset in between): check its cable"
                )
        aligned = self._align.process(frames)
        depth_frame = aligned.get_depth_frame()
        depth = np.asanyarray(depth_frame.get_data()).astype(np.float32) * self._scale
        arrival = self._rs.frame_metadata_value.time_of_arrival
        stamp = (
            depth_frame.get_frame_metadata(arrival) / 1000.0
            if depth_frame.supports_frame_metadata(arrival)
            else time.time()
        )
        self._count += 1
        return Frame(self.spec.serial, depth, float(stamp), self._count)

    def close(self) -> None:
        if self._pipeline is not None:
            try:
                self._pipeline.stop()
            except RuntimeError:
                pass  # already stopped
            finally:
                self._pipeline = None


# --- replay of a recorded session -------------------------------------------------------------------


class ReplayCamera(Camera):
    """Plays back the depth frames a session folder recorded (``steps/*.npz``), in order.

    Frames get fresh host timestamps so the loop's stale-frame check treats them as new captures.
    """

    kind = "replay"

    def __init__(self, spec, session: str | Path):
        super().__init__(spec)
        self.session = Path(session)
        self._files: list[Path] = []
        self._i = 0

    def open(self) -> None:
        steps = self.session / "steps"
        if not steps.is_dir():
            raise CameraError(f"replay: {steps} does not exist (not a hydo deploy session folder)")
        key = f"depth/{self.spec.serial}"
        self._files = []
        for f in sorted(steps.glob("*.npz")):
            with np.load(f) as z:
                if key in z.files:
                    self._files.append(f)
        if not self._files:
            raise CameraError(f"replay: {self.session} has no frames of camera {self.spec.label}")
        self._i = 0

    def close(self) -> None:
        self._files = []

    def capture(self) -> Frame:
        if self._i >= len(self._files):
            raise ReplayExhausted(
                f"replay: camera {self.spec.label} has played all {len(self._files)} recorded frames"
            )
        from robot.session_log import load_depth

        with np.load(self._files[self._i]) as z:
            depth = load_depth(z, self.spec.serial)
        self._i += 1
        return Frame(self.spec.serial, depth, time.time(), self._i)

    def __len__(self) -> int:
        return len(self._files)
