"""Scripted stand-ins for the hardware, for fault tests without a robot or a camera (robot-safety.md).

* :class:`SyntheticScene` ray-casts depth images of the bin floor and one box-shaped object for the
  cell's cameras (pinhole, OpenCV optical frames), so perception and registration run on exact,
  controllable frames: move the box, remove it, bump a camera, add NaNs.
* :class:`ScriptedCamera` serves those frames through the ``robot.cameras.Camera`` interface, one
  script entry per capture (``"nan"``, ``"stale"``, ``"timeout"``, ``"empty"``, a box pose, ...).
* :func:`fake_pyrealsense2` builds a ``pyrealsense2`` look-alike module (devices by serial, USB
  descriptor, pipelines that must be stopped, ``try_wait_for_frames`` timeouts, hardware resets) so
  ``RealSenseCamera`` itself is exercised.
* :func:`fake_panda_py` builds a ``panda_py`` look-alike module whose arm follows commands
  kinematically, records every motion it receives (optionally to a file, fsynced, for SIGKILL
  tests), reports robot mode and error flags, and fails as scripted: a reflex on a given move (with
  the latched-mode variant), panda-python's silent ``False``, a critical error, a lost connection,
  a contact force, a Ctrl-C, or ``SIGKILL`` of its own process. ``PandaExecutor`` runs on it unchanged.

Install the fake modules with ``sys.modules["panda_py"] = fake_panda_py(...)`` (tests use
pytest's ``monkeypatch.setitem``).
"""

from __future__ import annotations

import os
import signal
import sys
import time
import types
from dataclasses import dataclass, field

import numpy as np

from robot.arm import R_DOWN, rot_z
from robot.cameras import Camera, Frame
from robot.errors import CameraError
from robot.libfranka import OPERATOR_ACTIONS, RECOVERABLE_ERRORS, fingertip_to_ee

# --- synthetic depth -----------------------------------------------------------------------------------


@dataclass
class Box:
    """An upright box resting on the bin floor: centre (x, y) in the base frame, yaw about z."""

    size: tuple[float, float, float] = (0.06, 0.06, 0.06)  # m
    xy: tuple[float, float] = (0.5, 0.0)  # m
    yaw: float = 0.0  # rad


@dataclass
class SyntheticScene:
    """Depth of the bin floor (an infinite plane at the cell's floor height) and one box."""

    cell: object
    box: Box | None = field(default_factory=Box)
    noise: float = 0.0005  # m, Gaussian depth noise
    seed: int = 0

    def __post_init__(self):
        self.rng = np.random.default_rng(self.seed)
        self.camera_offsets: dict[str, np.ndarray] = {}  # serial -> (4, 4) applied to the true pose
        self._rays: dict = {}

    def bump(self, serial: str, shift_m: float = 0.02, turn_deg: float = 2.0) -> None:
        """Knock a camera: ``shift_m`` sideways and ``turn_deg`` of tilt in its own frame (its frames
        change; its calibration in the cell does not)."""
        a = np.deg2rad(turn_deg)
        T = np.eye(4)
        T[:3, :3] = [[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]]
        T[:3, 3] = [shift_m, 0.0, 0.0]
        self.camera_offsets[serial] = T

    def _boxes(self):
        """``(centre (3,), rotation (3, 3), half-size (3,))`` of the bin walls and the object."""
        cell, wall = self.cell, 0.01
        floor = cell.floor_z
        c = cell.bin_center
        hx, hy, h = cell.bin_size[0] / 2, cell.bin_size[1] / 2, cell.bin_size[2]
        I3 = np.eye(3)
        out = [
            (c + [hx + wall / 2, 0, h / 2], I3, np.array([wall / 2, hy + wall, h / 2])),
            (c + [-hx - wall / 2, 0, h / 2], I3, np.array([wall / 2, hy + wall, h / 2])),
            (c + [0, hy + wall / 2, h / 2], I3, np.array([hx + wall, wall / 2, h / 2])),
            (c + [0, -hy - wall / 2, h / 2], I3, np.array([hx + wall, wall / 2, h / 2])),
        ]
        if self.box is not None:
            b = self.box
            centre = np.array([b.xy[0], b.xy[1], floor + b.size[2] / 2])
            out.append((centre, rot_z(b.yaw), np.asarray(b.size, dtype=np.float64) / 2))
        return out

    def depth(self, spec) -> np.ndarray:
        """Z-depth (H, W) float32 metres seen by camera ``spec`` (0 where nothing is hit)."""
        H, W, K = spec.height, spec.width, spec.K
        T = spec.T_base_camera @ self.camera_offsets.get(spec.serial, np.eye(4))
        key = (spec.serial, T.tobytes())
        if key not in self._rays:
            v, u = np.mgrid[0:H, 0:W]
            rays_cam = np.stack(
                [(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones((H, W))], -1
            )  # z = 1
            self._rays[key] = rays_cam.reshape(-1, 3) @ T[:3, :3].T  # base-frame directions per unit depth
        d = self._rays[key]
        o = T[:3, 3]
        t_best = np.full(len(d), np.inf)
        floor = self.cell.floor_z
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (floor - o[2]) / d[:, 2]
        t_best = np.where((t > 0) & np.isfinite(t), t, t_best)
        for centre, R, half in self._boxes():
            ol = R.T @ (o - centre)  # ray origin and directions in the box frame
            dl = d @ R
            with np.errstate(divide="ignore", invalid="ignore"):
                t1 = (-half - ol) / dl
                t2 = (half - ol) / dl
            tmin = np.nanmax(np.minimum(t1, t2), axis=1)
            tmax = np.nanmin(np.maximum(t1, t2), axis=1)
            hit = (tmax >= tmin) & (tmin > 0)
            t_best = np.where(hit & (tmin < t_best), tmin, t_best)
        depth = np.where(np.isfinite(t_best), t_best, 0.0).reshape(H, W)
        if self.noise > 0:
            depth = np.where(depth > 0, depth + self.noise * self.rng.standard_normal(depth.shape), 0.0)
        return depth.astype(np.float32)


class ScriptedCamera(Camera):
    """A camera serving ``scene`` frames; ``script`` entries (one per capture, then plain frames):

    ``None`` a normal frame; ``"nan"`` NaN pixels; ``"stale"`` a 10 s old timestamp; ``"timeout"``
    raise ``CameraError``; a callable ``f(scene)`` run before rendering (move the box, ...).
    """

    kind = "scripted"

    def __init__(self, spec, scene: SyntheticScene, script: list | None = None):
        super().__init__(spec)
        self.scene = scene
        self.script = list(script or [])
        self.captures = 0
        self.is_open = False
        self.opened = 0
        self.closed = 0

    def open(self) -> None:
        self.is_open = True
        self.opened += 1

    def close(self) -> None:
        self.is_open = False
        self.closed += 1

    def capture(self) -> Frame:
        if not self.is_open:
            raise CameraError(f"camera {self.spec.label} is not open")
        entry = self.script[self.captures] if self.captures < len(self.script) else None
        self.captures += 1
        if entry == "timeout":
            raise CameraError(f"camera {self.spec.label} timed out")
        if callable(entry):
            entry(self.scene)
        depth = self.scene.depth(self.spec)
        stamp = time.time()
        if entry == "nan":
            depth[10:20, 10:20] = np.nan
        elif entry == "stale":
            stamp -= 10.0
        return Frame(self.spec.serial, depth, stamp, self.captures)


# --- a pyrealsense2 look-alike ----------------------------------------------------------------------------


def fake_pyrealsense2(scene: SyntheticScene, usb: dict | None = None, timeouts: dict | None = None):
    """A module with the ``pyrealsense2`` API that ``RealSenseCamera`` uses.

    Devices are the cell's cameras (by serial) found in ``scene.cell``; ``usb`` maps a serial to its
    USB descriptor (default "3.2"); ``timeouts`` maps a serial to the set of frame numbers (1-based,
    counting every ``try_wait_for_frames``) that time out. ``module.state`` records started
    pipelines, stops and hardware resets; starting a device twice without a stop raises
    "device busy", like librealsense after a crash.
    """
    usb = usb or {}
    timeouts = timeouts or {}
    rs = types.ModuleType("pyrealsense2")
    state = types.SimpleNamespace(running=set(), started=0, stopped=0, resets=[], waits={}, present=None)
    rs.state = state
    specs = {c.serial: c for c in scene.cell.cameras}
    state.present = set(specs)

    class camera_info:  # noqa: N801 (pyrealsense2's names)
        serial_number = "serial_number"
        usb_type_descriptor = "usb_type_descriptor"

    class stream:  # noqa: N801
        depth = "depth"
        color = "color"

    class format:  # noqa: N801
        z16 = "z16"
        rgb8 = "rgb8"

    class frame_metadata_value:  # noqa: N801
        time_of_arrival = "time_of_arrival"

    class _Device:
        def __init__(self, serial):
            self.serial = serial

        def get_info(self, key):
            return self.serial if key == camera_info.serial_number else usb.get(self.serial, "3.2")

        def supports(self, key):
            return True

        def hardware_reset(self):
            state.resets.append(self.serial)

        def first_depth_sensor(self):
            return types.SimpleNamespace(get_depth_scale=lambda: 0.001)

    class context:  # noqa: N801
        def query_devices(self):
            return [_Device(s) for s in specs if s in state.present]

    class config:  # noqa: N801
        def __init__(self):
            self.serial = None

        def enable_device(self, serial):
            self.serial = serial

        def enable_stream(self, *a):
            pass

    class _DepthFrame:
        def __init__(self, data):
            self.data = data

        def get_data(self):
            return self.data

        def supports_frame_metadata(self, key):
            return True

        def get_frame_metadata(self, key):
            return time.time() * 1000.0

    class _Frames:
        def __init__(self, data):
            self.depth = _DepthFrame(data)

        def get_depth_frame(self):
            return self.depth

    class pipeline:  # noqa: N801
        def __init__(self):
            self.serial = None

        def start(self, cfg):
            if cfg.serial in state.running:
                raise RuntimeError("xioctl(VIDIOC_S_FMT) failed: Device or resource busy")
            if cfg.serial not in state.present:
                raise RuntimeError("No device connected")
            self.serial = cfg.serial
            state.running.add(cfg.serial)
            state.started += 1
            return types.SimpleNamespace(get_device=lambda: _Device(cfg.serial))

        def stop(self):
            if self.serial not in state.running:
                raise RuntimeError("stop() cannot be called before start()")
            state.running.discard(self.serial)
            state.stopped += 1

        def try_wait_for_frames(self, timeout_ms=5000):
            n = state.waits[self.serial] = state.waits.get(self.serial, 0) + 1
            if n in timeouts.get(self.serial, ()):
                return False, None
            depth_m = scene.depth(specs[self.serial])
            return True, _Frames(np.round(depth_m / 0.001).astype(np.uint16))

    class align:  # noqa: N801
        def __init__(self, to):
            pass

        def process(self, frames):
            return frames

    for obj in (camera_info, stream, format, frame_metadata_value, context, config, pipeline, align):
        setattr(rs, obj.__name__, obj)
    return rs


# --- a panda_py look-alike ----------------------------------------------------------------------------------

#: Every libfranka error name a fake ``Errors`` object carries.
ERROR_NAMES = tuple(sorted(RECOVERABLE_ERRORS | set(OPERATOR_ACTIONS) - {"user_stop"}))
DEFAULT_F_T_EE = np.eye(4)
DEFAULT_F_T_EE[:3, :3] = rot_z(-np.pi / 4)
DEFAULT_F_T_EE[2, 3] = 0.1034  # Franka hand's default TCP in Desk


class _Errors:
    def __init__(self, names=()):
        for n in ERROR_NAMES:
            setattr(self, n, n in names)

    def __bool__(self):
        return any(getattr(self, n) for n in ERROR_NAMES)


@dataclass
class PandaScript:
    """What the fake arm does. Moves are numbered from 1 in the order the executor starts them.

    ``faults``: move number → one of ``"reflex"``, ``"reflex_latched"``, ``"false"`` (silent False
    with a reflex), ``"critical"`` (power limit), ``"user_stop"``, ``"comm_lost"``, ``"force"``
    (|F_ext| ramps past any threshold), ``"interrupt"`` (KeyboardInterrupt, a Ctrl-C), ``"sigkill"``.
    ``absent``: the connection fails. ``errors``: override the error names of a fault.
    """

    faults: dict[int, str] = field(default_factory=dict)
    absent: bool = False
    errors: dict[int, tuple[str, ...]] = field(default_factory=dict)
    record_path: str | None = None  # every received motion is appended here (fsynced) before it runs


def fake_panda_py(cell, script: PandaScript | None = None):
    """A module with the ``panda_py`` API that ``PandaExecutor`` uses; ``module.arm`` is the fake arm
    once connected (``module.connects`` counts connection attempts)."""
    script = script or PandaScript()
    pp = types.ModuleType("panda_py")
    pp.connects = 0
    pp.arm = None
    tip_to_ee = fingertip_to_ee(cell, DEFAULT_F_T_EE)

    class RobotMode:
        def __init__(self, name):
            self.name = name

    class _State:
        pass

    class CartesianImpedance:
        def __init__(self, impedance=None, damping_ratio=1.0, nullspace_stiffness=0.5, filter_coeff=1.0):
            self.target = None

        def set_control(self, position, orientation, q_nullspace=None):
            self.target = np.asarray(position, dtype=np.float64)
            arm = pp.arm
            if arm is not None and arm.controller is self and arm.healthy:
                arm.ee[:3, 3] = self.target  # the fake arm follows its reference exactly

    class _Context:
        def __init__(self, arm, max_runtime):
            self.arm, self.ticks, self.max_ticks = arm, 0, int(max(1.0, max_runtime) * 200)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            return False

        @property
        def num_ticks(self):
            return self.ticks

        def ok(self):  # panda-python sleeps here to keep the frequency; the fake runs flat out
            self.ticks += 1
            self.arm._tick(self.ticks)
            return self.arm.healthy and self.ticks < self.max_ticks

    class Panda:
        def __init__(self, hostname, name="panda", realtime_config=None):
            pp.connects += 1
            if script.absent:
                raise RuntimeError(
                    f"libfranka: Connection to FCI failed: Connection timeout ({hostname}:1337)"
                )
            self.hostname = hostname
            self.home_tip = None
            self.q = np.array(cell.home_joints, dtype=np.float64)
            self.ee = np.eye(4)
            self.mode = "kIdle"
            self.current = ()
            self.last = ()
            self.force = 0.0
            self.controller = None
            self.moves = 0
            self.received: list[tuple[str, list[float]]] = []
            self.recovers = 0
            self.collision_behavior = None
            self.connected = True
            self._fault = None
            pp.arm = self

        # state
        @property
        def healthy(self):
            return self.mode in ("kIdle", "kMove") and not self.current and self.connected

        def get_state(self):
            if not self.connected:
                raise RuntimeError("libfranka: NetworkException: connection lost")
            s = _State()
            s.q = self.q.copy()
            s.O_T_EE = self.ee.reshape(-1, order="F").copy()
            s.F_T_EE = DEFAULT_F_T_EE.reshape(-1, order="F").copy()
            s.O_F_ext_hat_K = np.array([self.force, 0, 0, 0, 0, 0], dtype=np.float64)
            s.robot_mode = RobotMode(self.mode)
            s.current_errors = _Errors(self.current)
            s.last_motion_errors = _Errors(self.last)
            return s

        def get_robot(self):
            arm = self

            class _Robot:
                def set_collision_behavior(self, *lists):
                    arm.collision_behavior = lists

            return _Robot()

        def raise_error(self):
            if self.current:
                raise RuntimeError(
                    f"libfranka: Move command aborted: motion aborted by reflex! [{', '.join(self.current)}]"
                )

        def recover(self):
            self.recovers += 1
            if self.mode == "kUserStopped":
                raise RuntimeError("libfranka: recovery failed: user stop pressed")
            self.current = ()
            self.mode = "kIdle"

        # motion
        def _receive(self, kind, values):
            self.moves += 1
            self.received.append((kind, [round(float(v), 6) for v in values]))
            if script.record_path:
                fd = os.open(script.record_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
                os.write(fd, f"{kind} {' '.join(f'{v:.6f}' for v in values)}\n".encode())
                os.fsync(fd)
                os.close(fd)
            self._fault = script.faults.get(self.moves)
            if self._fault == "sigkill":
                os.kill(os.getpid(), signal.SIGKILL)
            if self._fault == "interrupt":
                raise KeyboardInterrupt

        def _inject(self):
            fault, names = self._fault, script.errors.get(self.moves)
            self._fault = None
            if fault in ("reflex", "reflex_latched", "false"):
                self.mode = "kReflex"
                self.last = names or ("cartesian_reflex",)
                self.current = () if fault == "reflex_latched" else self.last
            elif fault == "critical":
                self.mode = "kReflex"
                self.current = self.last = names or ("power_limit_violation",)
            elif fault == "user_stop":
                self.mode = "kUserStopped"
            elif fault == "comm_lost":
                self.connected = False

        def _tick(self, ticks):
            if self._fault == "force":
                self.force = 2.0 * ticks
                return
            if self._fault is not None and ticks >= 3:
                self._inject()

        def start_controller(self, controller):
            if not self.healthy:
                raise RuntimeError("libfranka: cannot start a controller while the robot has an error")
            tip = (self.ee @ np.linalg.inv(tip_to_ee))[:3, 3]
            self.controller = controller
            self._receive("cartesian_from", tip)
            self.q = np.array(cell.home_joints, dtype=np.float64) + 0.3  # away from home (in view)
            self.force = 0.0

        def stop_controller(self):
            self.controller = None
            self.force = 0.0

        def create_context(self, frequency, max_runtime=0.0, max_iter=0):
            return _Context(self, max_runtime)

        def move_to_joint_position(self, waypoints, speed_factor=0.2, **kw):
            q = np.asarray(waypoints[0] if np.ndim(waypoints) == 2 else waypoints, dtype=np.float64)
            self._receive("joint", q)
            if self._fault is not None:
                self._inject()
                return False  # panda-python's silent False
            self.q = q.copy()
            self.ee = self.home_ee.copy()
            return True

    def _home_ee():
        from robot.arm import ArmKinematics

        p, _ = ArmKinematics.for_cell(cell).fk(cell.home_joints)
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_DOWN, p
        return T @ tip_to_ee

    orig_init = Panda.__init__

    def init(self, *a, **k):
        orig_init(self, *a, **k)
        self.home_ee = _home_ee()
        self.ee = self.home_ee.copy()

    Panda.__init__ = init
    pp.Panda = Panda
    pp.controllers = types.SimpleNamespace(CartesianImpedance=CartesianImpedance)
    pp.libfranka = types.SimpleNamespace(RobotMode=RobotMode)
    return pp


def install(monkeypatch_or_none, name: str, module) -> None:
    """Put a fake module in ``sys.modules`` (through pytest's monkeypatch when given)."""
    if monkeypatch_or_none is not None:
        monkeypatch_or_none.setitem(sys.modules, name, module)
        if name == "panda_py":
            monkeypatch_or_none.setitem(sys.modules, "panda_py.controllers", module.controllers)
    else:
        sys.modules[name] = module
        if name == "panda_py":
            sys.modules["panda_py.controllers"] = module.controllers


# --- a franky look-alike ------------------------------------------------------------------------------------


@dataclass
class FrankyScript:
    """What the fake FR3 does; moves are numbered from 1. ``faults``: move → ``"reflex"``
    (``ControlException``), ``"force"`` (the force reaction fires and ``move`` returns normally, as
    franky's reactions do), ``"deadline"`` (the time reaction fires halfway, likewise),
    ``"comm_lost"`` (``NetworkException``), ``"planner"`` (franky's trajectory generator fails part-way
    with a plain ``RuntimeError``, no error flag, as franky-sim does now and then). ``absent``:
    connecting fails."""

    faults: dict[int, str] = field(default_factory=dict)
    absent: bool = False


def fake_franky(cell, script: FrankyScript | None = None):
    """A module with the ``franky`` API that ``FR3Executor`` uses; ``module.robot`` once connected."""
    script = script or FrankyScript()
    fr = types.ModuleType("franky")
    fr.robot = None
    fr.connects = 0
    tip_to_ee = fingertip_to_ee(cell, DEFAULT_F_T_EE)

    class Exception_(Exception):  # franky.Exception
        pass

    class ControlException(Exception_):
        pass

    class NetworkException(Exception_):
        pass

    fr.Exception, fr.ControlException, fr.NetworkException = Exception_, ControlException, NetworkException
    fr.RealtimeConfig = types.SimpleNamespace(Enforce="Enforce", Ignore="Ignore")
    fr.ReferenceType = types.SimpleNamespace(Absolute="Absolute", Relative="Relative")

    class _Mode:
        def __init__(self, name):
            self.name = name

    class Measure:
        def __init__(self, expr):
            self.expr = expr

        def __mul__(self, o):
            return Measure(f"({self.expr})*({getattr(o, 'expr', o)})")

        def __add__(self, o):
            return Measure(f"({self.expr})+({getattr(o, 'expr', o)})")

        def __gt__(self, v):
            return types.SimpleNamespace(expr=f"{self.expr} > {v}", threshold=v)

    Measure.FORCE_X, Measure.FORCE_Y, Measure.FORCE_Z = Measure("F_x"), Measure("F_y"), Measure("F_z")
    Measure.REL_TIME = Measure("t_rel")
    fr.Measure = Measure

    class Affine:
        def __init__(self, matrix=None):
            self.matrix = np.eye(4) if matrix is None else np.asarray(matrix, dtype=np.float64)

    class CartesianStopMotion:
        def __init__(self, relative_dynamics_factor=1.0):
            pass

    class JointStopMotion:
        def __init__(self, relative_dynamics_factor=1.0):
            pass

    class Reaction:
        def __init__(self, condition, motion):
            self.condition, self.motion, self.callbacks = condition, motion, []

        def register_callback(self, cb):
            self.callbacks.append(cb)

    class CartesianMotion:
        def __init__(self, target, reference_type="Absolute", relative_dynamics_factor=1.0, **kw):
            self.target, self.reference_type = target, reference_type
            self.relative_dynamics_factor, self.reactions = relative_dynamics_factor, []

        def add_reaction(self, reaction):
            self.reactions.append(reaction)

    class JointState:
        def __init__(self, position):
            self.position = np.asarray(position, dtype=np.float64)

    class JointMotion:
        def __init__(self, target, reference_type="Absolute", relative_dynamics_factor=1.0, **kw):
            self.target, self.relative_dynamics_factor, self.reactions = target, relative_dynamics_factor, []

        def add_reaction(self, reaction):
            self.reactions.append(reaction)

    for obj in (
        Affine,
        CartesianStopMotion,
        JointStopMotion,
        Reaction,
        CartesianMotion,
        JointState,
        JointMotion,
    ):
        setattr(fr, obj.__name__, obj)

    class Robot:
        def __init__(self, fci_hostname, relative_dynamics_factor=1.0, default_torque_threshold=20.0,
                     default_force_threshold=30.0, realtime_config="Enforce", **kw):  # fmt: skip
            fr.connects += 1
            if script.absent:
                raise NetworkException(f"libfranka: Connection timeout ({fci_hostname})")
            self.realtime_config = realtime_config
            self.relative_dynamics_factor = relative_dynamics_factor
            self.translation_velocity_limit = 3.0  # m/s (the FR3's)
            self.collision = None
            self.recoveries = 0
            self.moves: list = []
            self.q = np.array(cell.home_joints, dtype=np.float64)
            from robot.arm import ArmKinematics

            p, _ = ArmKinematics.for_cell(cell).fk(cell.home_joints)
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R_DOWN, p
            self.home_ee = T @ tip_to_ee
            self.ee = self.home_ee.copy()
            self.mode, self.current, self.last = "Idle", (), ()
            fr.robot = self

        @property
        def state(self):
            return types.SimpleNamespace(
                robot_mode=_Mode(self.mode),
                current_errors=_Errors(self.current),
                last_motion_errors=_Errors(self.last),
                F_T_EE=DEFAULT_F_T_EE.reshape(-1, order="F"),
            )

        @property
        def current_pose(self):
            return types.SimpleNamespace(end_effector_pose=Affine(self.ee))

        @property
        def current_joint_positions(self):
            return self.q.copy()

        def recover_from_errors(self):
            self.recoveries += 1
            self.mode, self.current = "Idle", ()
            return True

        def set_collision_behavior(self, torque, force):
            self.collision = (torque, force)

        def stop(self):
            pass

        def move(self, motion, asynchronous=False):
            self.moves.append(motion)
            fault = script.faults.get(len(self.moves))
            if self.mode != "Idle":
                raise ControlException("libfranka: Move command rejected: robot is in reflex mode")
            if fault == "comm_lost":
                raise NetworkException("libfranka: UDP receive: Timeout")
            if fault == "reflex":
                self.mode, self.current = "Reflex", ("cartesian_reflex",)
                self.last = self.current
                raise ControlException(
                    "libfranka: Move command aborted: motion aborted by reflex! [cartesian_reflex]"
                )
            if isinstance(motion, JointMotion):
                self.q = motion.target.position.copy()
                self.ee = self.home_ee.copy()
                return
            target = motion.target.matrix
            if fault == "planner":
                self.ee[:3, 3] = (self.ee[:3, 3] + target[:3, 3]) / 2
                raise RuntimeError("Motion planner failed with error code -111")
            if fault in ("force", "deadline"):  # the reaction fires halfway: franky returns normally
                self.ee[:3, 3] = (self.ee[:3, 3] + target[:3, 3]) / 2
                measure = "F_x" if fault == "force" else "t_rel"
                for r in motion.reactions:
                    if measure in r.condition.expr:
                        for cb in r.callbacks:
                            cb(None, 0.1, 0.1)
                return
            self.ee = target.copy()
            self.q = np.array(cell.home_joints, dtype=np.float64) + 0.3

    fr.Robot = Robot
    return fr
