"""The cell file (``cell.yaml``): everything deploy knows about the physical setup. Its one home.

A cell names the robot and its address, the gripper's fingertip offset, every speed and force limit,
the bin, the fingertip's workspace box and each depth camera's serial, intrinsics and extrinsics.
:func:`load_cell` validates all of it on load and refuses with one line naming the key; nothing
opens a camera or connects to a robot before the cell has loaded. ``robot/cell.example.yaml`` is a
documented example and, unchanged, the cell of the MuJoCo twin (``--robot sim`` without ``--cell``).

Frames and units: metres, seconds, newtons, radians. Every position is in the **robot base frame**
(z up, as the arm stands). The bin frame of training (``sim.primitive``: floor top at z = 0, centred
at x = y = 0) is the base frame shifted by ``bin.center_m``; the policy is translation invariant (its
encoder centres positions on the object), so base-frame points go to the network as they are.
Cameras: ``T_base_camera`` is the pose (4, 4) of the camera's **optical** frame (OpenCV: x right,
y down, z forward) in the base frame, as ``cv2.calibrateHandEye`` gives it.

Force settings must be consistent (``robot-safety.md``): with a Cartesian stiffness ``K`` and the
longest push segment ``L`` (``PUSH_STEP_M · √3``: a motion in [-1, 1]³), a blocked segment alone
pushes with at most ``K · L``, which must not exceed the contact-force stop ``F_stop``, and the stop
must fire before the robot's collision reflex: ``K · L ≤ F_stop < F_collision − 5 N``.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import TypeAdapter, ValidationError

from robot.errors import CellError, GoalError
from sim.primitive import FLOOR_CLEARANCE_M, FORCE_STOP_N, PUSH_STEP_M, Workspace
from sim.schema import STRICT, one_line

CELL_VERSION = 1
EXAMPLE_CELL = Path(__file__).parent / "cell.example.yaml"
ROBOT_TYPES = ("panda", "fr3", "sim")
MAX_PUSH_SEGMENT_M = PUSH_STEP_M * math.sqrt(3.0)  # a push step of 3 cm · motion, motion in [-1, 1]^3
FORCE_MARGIN_N = 5.0  # F_stop must stay this far below the collision reflex threshold
#: Hard caps the cell may not exceed (robot-safety.md: "speed limits worth adopting").
MAX_TRANSIT_SPEED = 0.10  # m/s
MAX_PUSH_SPEED = 0.05  # m/s
#: The fingertip offset is the flange-to-fingertip distance; anything outside this range is a typo.
FINGERTIP_OFFSET_RANGE_M = (0.05, 0.30)


@dataclass(frozen=True)
class CameraSpec:
    """One depth camera: serial, image size, pinhole intrinsics and optical-frame pose in the base frame."""

    serial: str
    width: int  # pixels
    height: int  # pixels
    K: np.ndarray  # (3, 3) intrinsics of the (aligned) depth image
    T_base_camera: np.ndarray  # (4, 4) optical frame (x right, y down, z forward) in the base frame
    fps: int = 30
    name: str = ""  # human-readable label, e.g. "front"

    @property
    def label(self) -> str:
        return f"{self.name or 'camera'} ({self.serial})"


@dataclass(frozen=True)
class Limits:
    """Speed and force limits; each is logged when a robot connects and set on the robot explicitly."""

    transit_speed: float = 0.10  # m/s, fingertip speed in free space (approach, retract, home)
    push_speed: float = 0.05  # m/s, fingertip speed from pre-contact through the pushes
    cartesian_stiffness: float = 500.0  # N/m, translational impedance of the arm's controller
    rotational_stiffness: float = 30.0  # N·m/rad
    force_stop: float = FORCE_STOP_N  # N, contact-force stop: a push is stopped when |F_ext| exceeds it
    collision_force: float = 40.0  # N, the robot's Cartesian collision reflex threshold
    collision_torque: float = 30.0  # N·m, the robot's joint collision reflex threshold
    motion_timeout: float = 20.0  # s, deadline on every single move
    approach_height: float = 0.15  # m above the bin floor: transit height over the bin
    position_tolerance: float = 0.01  # m, a move ending further than this from its target is short


@dataclass(frozen=True)
class Perception:
    """Segmentation and registration thresholds (see ``robot.perception`` and ``robot.registration``)."""

    min_object_points: int = 100  # fused object points below this: refused as an empty/tiny mask
    max_background_mismatch: float = 0.10  # fraction of bin pixels off the background: camera moved
    background_frames: int = 10  # frames averaged (nanmedian) by capture-background
    registration_max_rmse: float = 0.004  # m, RMS of inlier correspondences after ICP
    # fraction of the object points the goal would show (registration.goal_visible) with a goal point
    # within 1 cm
    registration_min_inliers: float = 0.8
    # fraction of the object points the goal would show at all: under it, too little to check a fit
    registration_min_overlap: float = 0.3
    # success is claimed only this far inside the 3 cm threshold (registration's distance error near
    # the goal: 1.7 mm p90 on 6D goals, docs/results.md)
    success_margin: float = 0.003
    max_frame_age: float = 1.0  # s, a frame older than this (or than the last motion) is stale
    warmup_frames: int = 5  # frames dropped after a camera starts (auto-exposure)


@dataclass(frozen=True)
class Cell:
    """A validated cell. Build with :func:`load_cell` (or :func:`parse_cell` from a dict)."""

    robot_type: str
    address: str
    home_joints: np.ndarray  # (7,) rad: the observe pose, arm out of every camera's view
    fingertip_offset: np.ndarray  # (3,) m: fingertip in the flange frame
    hand_yaw: float  # rad: the hand's mounting angle about the flange z axis
    limits: Limits
    bin_center: np.ndarray  # (3,) m: centre of the bin floor's top surface, base frame
    bin_size: np.ndarray  # (3,) m: inner x, y size and wall height
    workspace: Workspace  # fingertip box, base frame; floor_z = bin floor
    cameras: tuple[CameraSpec, ...]
    perception: Perception = field(default_factory=Perception)
    twin_depth_noise: float = 0.001  # m, Gaussian noise the twin adds to its rendered depth
    source: str = "<dict>"  # where the cell came from (file path), for messages and logs
    raw: dict = field(default_factory=dict, repr=False)  # the parsed YAML, logged with each session

    @property
    def floor_z(self) -> float:
        return float(self.bin_center[2])

    @property
    def bin_low(self) -> np.ndarray:
        """Inner bin box low corner (3,): floor top and inner wall faces."""
        return self.bin_center - np.array([self.bin_size[0] / 2, self.bin_size[1] / 2, 0.0])

    @property
    def bin_high(self) -> np.ndarray:
        """Inner bin box high corner (3,): inner wall faces and rim height."""
        return self.bin_center + np.array([self.bin_size[0] / 2, self.bin_size[1] / 2, self.bin_size[2]])

    @property
    def approach_z(self) -> float:
        """Fingertip height (base frame) of every transit over the bin."""
        return self.floor_z + self.limits.approach_height

    def summary(self) -> dict:
        """The safety-relevant settings, for the session log and the start-up message."""
        lim = self.limits
        return {
            "robot_type": self.robot_type,
            "address": self.address,
            "fingertip_offset_m": self.fingertip_offset.tolist(),
            "transit_speed_mps": lim.transit_speed,
            "push_speed_mps": lim.push_speed,
            "cartesian_stiffness_npm": lim.cartesian_stiffness,
            "force_stop_n": lim.force_stop,
            "collision_force_n": lim.collision_force,
            "collision_torque_nm": lim.collision_torque,
            "motion_timeout_s": lim.motion_timeout,
            "workspace_low_m": list(self.workspace.low),
            "workspace_high_m": list(self.workspace.high),
            "cameras": [c.serial for c in self.cameras],
        }


# --- parsing ---------------------------------------------------------------------------------------


class _Reader:
    """Typed access to a nested dict with one-line errors naming the dotted key and the file."""

    def __init__(self, data: dict, source: str, prefix: str = ""):
        self.data, self.source, self.prefix = data, source, prefix

    def _err(self, key: str, msg: str) -> CellError:
        return CellError(f"{self.source}: `{self.prefix}{key}` {msg}")

    def only(self, *keys: str) -> _Reader:
        """Refuse keys this section does not know (a typo must not silently fall back to a default)."""
        unknown = sorted(map(str, set(self.data) - set(keys)))  # str: YAML keys may be numbers
        if unknown:
            raise self._err(unknown[0], f"is not a known key here (known: {', '.join(keys)})")
        return self

    def section(self, key: str, required: bool = True) -> _Reader:
        v = self.data.get(key)
        if v is None:
            if required:
                raise self._err(key, "is missing")
            v = {}
        if not isinstance(v, dict):
            raise self._err(key, f"must be a mapping. Got {type(v).__name__}.")
        return _Reader(v, self.source, f"{self.prefix}{key}.")

    def has(self, key: str) -> bool:
        return self.data.get(key) is not None

    def number(self, key: str, default=None, low=None, high=None, strict_low=False) -> float:
        v = self.data.get(key, default)
        if v is None:
            raise self._err(key, "is missing")
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise self._err(key, f"must be a finite number. Got {v!r}.")
        v = float(v)
        if low is not None and (v <= low if strict_low else v < low):
            raise self._err(key, f"must be {'>' if strict_low else '>='} {low}. Got {v}.")
        if high is not None and v > high:
            raise self._err(key, f"must be <= {high}. Got {v}.")
        return v

    def integer(self, key: str, default=None, low=None) -> int:
        v = self.data.get(key, default)
        if v is None:
            raise self._err(key, "is missing")
        if isinstance(v, bool) or not isinstance(v, int):
            raise self._err(key, f"must be an integer. Got {v!r}.")
        if low is not None and v < low:
            raise self._err(key, f"must be >= {low}. Got {v}.")
        return int(v)

    def string(self, key: str, default=None, choices=None) -> str:
        v = self.data.get(key, default)
        if v is None:
            raise self._err(key, "is missing")
        if isinstance(v, int | float) and not isinstance(v, bool):
            v = str(v)  # YAML reads an all-digit serial as a number
        if not isinstance(v, str) or not v:
            raise self._err(key, f"must be a non-empty string. Got {v!r}.")
        if choices is not None and v not in choices:
            raise self._err(key, f"must be one of {list(choices)}. Got {v!r}.")
        return v

    def array(self, key: str, shape: tuple[int, ...], default=None) -> np.ndarray:
        v = self.data.get(key, default)
        if v is None:
            raise self._err(key, "is missing")
        # numpy would read ``true`` as 1.0 and ``"0.5"`` as 0.5: the strict schema of nested lists of
        # finite numbers refuses both (sim.schema.STRICT) before numpy sees the value.
        try:
            _number_lists(len(shape)).validate_python(v)
        except ValidationError as e:
            raise CellError(one_line(e, self.source, prefix=f"{self.prefix}{key}")) from None
        a = np.asarray(v, dtype=np.float64)
        if a.shape != shape:
            raise self._err(key, f"must have shape {shape}. Got {a.shape}.")
        if not np.all(np.isfinite(a)):
            raise self._err(key, "must be finite (no NaN or inf)")
        return a


@functools.cache
def _number_lists(rank: int) -> TypeAdapter:
    """Strict pydantic type of a rank-``rank`` nested list of finite numbers (a vector, a matrix)."""
    kind: Any = float
    for _ in range(rank):
        kind = list[kind]
    return TypeAdapter(kind, config=STRICT)


def _camera(r: _Reader, index: int) -> CameraSpec:
    r.only("name", "serial", "width", "height", "fps", "intrinsics", "T_base_camera")
    serial = r.string("serial")
    width, height = r.integer("width", low=16), r.integer("height", low=16)
    intr = r.section("intrinsics").only("fx", "fy", "cx", "cy")
    fx, fy = intr.number("fx", low=0, strict_low=True), intr.number("fy", low=0, strict_low=True)
    cx, cy = intr.number("cx", low=0, high=width), intr.number("cy", low=0, high=height)
    K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    T = r.array("T_base_camera", (4, 4))
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6):
        raise r._err("T_base_camera", f"must end with the row [0, 0, 0, 1]. Got {T[3].tolist()}.")
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4) or np.linalg.det(R) < 0:
        raise r._err("T_base_camera", "must be a rigid transform (orthonormal rotation, det +1)")
    return CameraSpec(
        serial=serial,
        width=width,
        height=height,
        K=K,
        T_base_camera=T,
        fps=r.integer("fps", default=30, low=1),
        name=r.string("name", default=f"camera{index}"),
    )


def parse_cell(data: dict, source: str = "<dict>") -> Cell:
    """Validate a parsed cell (the YAML's top-level mapping); raise ``CellError`` naming the key."""
    if not isinstance(data, dict):
        raise CellError(f"{source}: a cell file must be a YAML mapping. Got {type(data).__name__}.")
    top = _Reader(data, source).only(
        "version", "robot", "tool", "limits", "bin", "workspace", "cameras", "perception", "twin"
    )
    version = top.integer("version", default=CELL_VERSION)
    if version != CELL_VERSION:
        raise CellError(f"{source}: cell version {version}, this hydo reads version {CELL_VERSION}")

    rob = top.section("robot").only("type", "address", "home_joints")
    robot_type = rob.string("type", choices=ROBOT_TYPES)
    address = rob.string("address", default="127.0.0.1")
    home = rob.array("home_joints", (7,))

    tool = top.section("tool").only("fingertip_offset_m", "hand_yaw_deg")
    if not tool.has("fingertip_offset_m"):
        raise CellError(
            f"{source}: `tool.fingertip_offset_m` is missing: measure the fingertip (bottom centre of the "
            "closed fingers) in the flange frame, e.g. [0, 0, 0.1124] for a Franka hand. hydo never "
            "assumes a default tool offset."
        )
    offset = tool.array("fingertip_offset_m", (3,))
    lo, hi = FINGERTIP_OFFSET_RANGE_M
    if not lo <= np.linalg.norm(offset) <= hi:
        raise CellError(
            f"{source}: `tool.fingertip_offset_m` is {np.linalg.norm(offset):.3f} m from the flange; "
            f"expected {lo}-{hi} m (metres, not millimetres?)"
        )
    hand_yaw = math.radians(tool.number("hand_yaw_deg", default=-45.0, low=-180.0, high=180.0))

    lim = top.section("limits").only(
        "transit_speed_mps",
        "push_speed_mps",
        "cartesian_stiffness_npm",
        "rotational_stiffness_nmprad",
        "force_stop_n",
        "collision_force_n",
        "collision_torque_nm",
        "motion_timeout_s",
        "approach_height_m",
        "position_tolerance_m",
    )
    limits = Limits(
        transit_speed=lim.number("transit_speed_mps", 0.10, low=0, high=MAX_TRANSIT_SPEED, strict_low=True),
        push_speed=lim.number("push_speed_mps", 0.05, low=0, high=MAX_PUSH_SPEED, strict_low=True),
        cartesian_stiffness=lim.number("cartesian_stiffness_npm", low=0, strict_low=True),
        rotational_stiffness=lim.number("rotational_stiffness_nmprad", 30.0, low=0, strict_low=True),
        force_stop=lim.number("force_stop_n", low=0, strict_low=True),
        collision_force=lim.number("collision_force_n", low=0, strict_low=True),
        collision_torque=lim.number("collision_torque_nm", 30.0, low=0, strict_low=True),
        motion_timeout=lim.number("motion_timeout_s", 20.0, low=0, high=120.0, strict_low=True),
        approach_height=lim.number("approach_height_m", 0.15, low=0.05, high=0.5),
        position_tolerance=lim.number("position_tolerance_m", 0.01, low=0, high=0.05, strict_low=True),
    )
    blocked = limits.cartesian_stiffness * MAX_PUSH_SEGMENT_M
    if blocked > limits.force_stop:
        raise CellError(
            f"{source}: inconsistent force settings: cartesian_stiffness_npm {limits.cartesian_stiffness:g} "
            f"x longest push segment {MAX_PUSH_SEGMENT_M:.3f} m = {blocked:.1f} N exceeds force_stop_n "
            f"{limits.force_stop:g} N (lower the stiffness or raise the stop)"
        )
    if limits.force_stop >= limits.collision_force - FORCE_MARGIN_N:
        raise CellError(
            f"{source}: inconsistent force settings: force_stop_n {limits.force_stop:g} N must be below "
            f"collision_force_n {limits.collision_force:g} N - {FORCE_MARGIN_N:g} N, or the robot's reflex "
            "fires before hydo's contact-force stop"
        )

    b = top.section("bin").only("center_m", "inner_size_m")
    bin_center = b.array("center_m", (3,))
    bin_size = b.array("inner_size_m", (3,))
    if np.any(bin_size <= 0.02):
        raise CellError(
            f"{source}: `bin.inner_size_m` must be > 0.02 m on every axis. Got {bin_size.tolist()}."
        )

    ws = top.section("workspace").only("low_m", "high_m")
    low, high = ws.array("low_m", (3,)), ws.array("high_m", (3,))
    floor = float(bin_center[2])
    if not np.all(high > low):
        raise CellError(f"{source}: `workspace` must have low_m < high_m on x, y, z")
    inner_lo = bin_center[:2] - bin_size[:2] / 2
    inner_hi = bin_center[:2] + bin_size[:2] / 2
    if np.any(low[:2] < inner_lo - 1e-9) or np.any(high[:2] > inner_hi + 1e-9):
        raise CellError(
            f"{source}: `workspace` x/y must lie inside the bin's inner walls "
            f"{inner_lo.round(3).tolist()}..{inner_hi.round(3).tolist()} m"
        )
    if low[2] < floor - 1e-9 or low[2] > floor + FLOOR_CLEARANCE_M:
        raise CellError(
            f"{source}: `workspace.low_m` z must be between the bin floor ({floor:.3f} m) and "
            f"floor + {FLOOR_CLEARANCE_M} m. Got {low[2]:.3f}."
        )
    approach_z = floor + limits.approach_height
    if approach_z > high[2]:
        raise CellError(
            f"{source}: the transit height (bin floor + approach_height_m = {approach_z:.3f} m) is above "
            f"`workspace.high_m` z ({high[2]:.3f} m)"
        )
    if approach_z < bin_center[2] + bin_size[2]:
        raise CellError(
            f"{source}: `limits.approach_height_m` {limits.approach_height:g} m is below the bin rim "
            f"({bin_size[2]:g} m above the floor)"
        )
    workspace = Workspace(tuple(low.tolist()), tuple(high.tolist()), floor_z=floor)

    cams = data.get("cameras")
    if not isinstance(cams, list) or not cams:
        raise CellError(f"{source}: `cameras` must be a non-empty list of cameras")
    cameras = []
    for i, c in enumerate(cams):
        if not isinstance(c, dict):
            raise CellError(f"{source}: `cameras[{i}]` must be a mapping")
        cameras.append(_camera(_Reader(c, source, f"cameras[{i}]."), i))
    serials = [c.serial for c in cameras]
    if len(set(serials)) != len(serials):
        raise CellError(f"{source}: camera serials must be unique. Got {serials}.")

    per = top.section("perception", required=False).only(
        "min_object_points",
        "max_background_mismatch",
        "background_frames",
        "registration_max_rmse_m",
        "registration_min_inliers",
        "registration_min_overlap",
        "success_margin_m",
        "max_frame_age_s",
        "warmup_frames",
    )
    perception = Perception(
        min_object_points=per.integer("min_object_points", 100, low=8),
        max_background_mismatch=per.number("max_background_mismatch", 0.10, low=0, high=1),
        background_frames=per.integer("background_frames", 10, low=1),
        registration_max_rmse=per.number("registration_max_rmse_m", 0.004, low=0, high=0.05, strict_low=True),
        registration_min_inliers=per.number("registration_min_inliers", 0.8, low=0, high=1),
        registration_min_overlap=per.number("registration_min_overlap", 0.3, low=0, high=1),
        success_margin=per.number("success_margin_m", 0.003, low=0, high=0.02),
        max_frame_age=per.number("max_frame_age_s", 1.0, low=0, strict_low=True),
        warmup_frames=per.integer("warmup_frames", 5, low=0),
    )
    twin = top.section("twin", required=False).only("depth_noise_m")
    return Cell(
        robot_type=robot_type,
        address=address,
        home_joints=home,
        fingertip_offset=offset,
        hand_yaw=hand_yaw,
        limits=limits,
        bin_center=bin_center,
        bin_size=bin_size,
        workspace=workspace,
        cameras=tuple(cameras),
        perception=perception,
        twin_depth_noise=twin.number("depth_noise_m", 0.001, low=0, high=0.05),
        source=source,
        raw=data,
    )


def load_cell(path: str | Path | None = None, reach: bool = True) -> Cell:
    """Load and validate a cell file; ``None`` loads the shipped example (the MuJoCo twin's cell).

    ``reach``: also refuse a workspace the arm cannot reach (:func:`check_reach`, ~10 ms)."""
    import yaml

    path = Path(path) if path is not None else EXAMPLE_CELL
    if not path.is_file():
        raise CellError(
            f"cell file {path} does not exist: start from {EXAMPLE_CELL.name} (`cp {EXAMPLE_CELL} cell.yaml`)"
        )
    try:
        data = yaml.safe_load(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError:
        raise CellError(f"{path}: not a text file (not UTF-8): not a cell file") from None
    except yaml.YAMLError as e:
        first = str(e).splitlines()[0] if str(e) else e.__class__.__name__
        raise CellError(f"{path}: not valid YAML ({first})") from None
    cell = parse_cell(data, str(path))
    if reach:
        check_reach(cell)
    return cell


def reach_points(cell: Cell) -> np.ndarray:
    """(27, 3) fingertip targets every plan may need: a 3 x 3 grid over the workspace's x/y (corners,
    edge midpoints, centre) at the lowest push height (floor + clearance), halfway up and at the
    transit height. The corners alone missed the worst place: with the bin 0.50 m in front of a
    Panda's base, a push at the middle of the near wall needs joint 4 within 0.05 rad of its limit
    (the arm folds back over itself) while all eight corners pass, and the twin refused such plans
    mid-episode."""
    lo, hi = np.array(cell.workspace.low), np.array(cell.workspace.high)
    floor = cell.floor_z + FLOOR_CLEARANCE_M
    zs = (floor, (floor + cell.approach_z) / 2, cell.approach_z)
    xs, ys = np.linspace(lo[0], hi[0], 3), np.linspace(lo[1], hi[1], 3)
    return np.array([[x, y, z] for x in xs for y in ys for z in zs])


def check_reach(cell: Cell) -> None:
    """Refuse, at load, a cell whose workspace the arm cannot reach with the hand pointing down.

    The arm's own kinematics (``robot.arm.ArmKinematics``, the model every plan is checked with):
    IK from the home pose to the workspace centre at transit height, then from there to each corner
    of ``reach_points``; each must converge and keep every joint ``JOINT_MARGIN_RAD`` inside its
    limits, as ``solve_path`` demands of every plan. Without this a bin out of reach loads and every
    plan is then refused one by one (in the twin: episodes "end", exit 0).
    """
    from robot.arm import IK_TOL_POS_M, IK_TOL_ROT_RAD, ArmKinematics

    kin = ArmKinematics.for_cell(cell)
    lo, hi = np.array(cell.workspace.low), np.array(cell.workspace.high)
    centre = np.r_[(lo[:2] + hi[:2]) / 2, cell.approach_z]
    q_centre, _, _ = kin.ik(centre, cell.home_joints, iters=300)
    for p in (centre, *reach_points(cell)):
        q, ep, er = kin.ik(p, q_centre, iters=300)
        margin, joint = kin.margin_of(q)
        where = f"{cell.source}: the workspace point {np.round(p, 3).tolist()} m (bin.center_m {cell.bin_center.tolist()})"
        if ep > IK_TOL_POS_M or er > IK_TOL_ROT_RAD:
            raise CellError(
                f"{where} is beyond the {cell.robot_type} arm's reach with the hand pointing down "
                f"(IK error {ep * 1000:.0f} mm, {np.degrees(er):.0f} deg): move the bin closer or fix the cell"
            )
        if margin < kin.margin:
            raise CellError(
                f"{where} needs joint {joint + 1} within {margin:.3f} rad of its limit (margin {kin.margin} "
                "rad): move the bin"
            )


#: A goal cloud point may stick out of the bin's inner walls by this much (depth noise at the walls).
GOAL_WALL_TOLERANCE_M = 0.01


def check_goal(cell: Cell, points: np.ndarray, source: str) -> None:
    """Refuse a goal cloud (base frame) the cell cannot hold: any point outside the bin's inner walls
    (x/y, ``GOAL_WALL_TOLERANCE_M``) or below its floor, or its centre outside the fingertip's
    workspace box (x/y). ``source`` says where the goal came from (a file, ``--goal-offset DX,DY``)."""
    pts = np.asarray(points, dtype=np.float64)
    tol = GOAL_WALL_TOLERANCE_M
    lo, hi = cell.bin_low[:2] - tol, cell.bin_high[:2] + tol
    outside = np.any((pts[:, :2] < lo) | (pts[:, :2] > hi), axis=1) | (pts[:, 2] < cell.floor_z - tol)
    centre = pts.mean(0)
    if outside.any():
        raise GoalError(
            f"{source}: the goal puts {int(outside.sum())} of {len(pts)} object points outside the bin "
            f"(inner walls x/y {np.round(cell.bin_low[:2], 3).tolist()}..{np.round(cell.bin_high[:2], 3).tolist()} m, "
            f"goal centre {np.round(centre, 3).tolist()} m): refused before any motion"
        )
    wlo, whi = np.array(cell.workspace.low[:2]), np.array(cell.workspace.high[:2])
    if np.any(centre[:2] < wlo) or np.any(centre[:2] > whi):
        raise GoalError(
            f"{source}: the goal's centre {np.round(centre, 3).tolist()} m is outside the workspace "
            f"x/y {np.round(wlo, 3).tolist()}..{np.round(whi, 3).tolist()} m: refused before any motion"
        )


def check_goal_offset(cell: Cell, dx: float, dy: float, source: str) -> None:
    """Refuse a ``--goal-offset`` no start in the workspace can satisfy (a shift larger than the
    workspace along x or y), before anything opens; ``check_goal`` then checks each episode's goal
    cloud once the start is seen, still before any motion."""
    size = np.array(cell.workspace.high[:2]) - np.array(cell.workspace.low[:2])
    for axis, d, extent in (("x", dx, size[0]), ("y", dy, size[1])):
        if abs(d) >= extent:
            raise GoalError(
                f"{source}: a shift of {d:+.3f} m along {axis} leaves the workspace ({extent:.3f} m wide "
                "along it) from any start: refused"
            )
