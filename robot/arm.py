"""The Franka arm's MuJoCo model and kinematics: plan checks for every executor, and the twin's arm.

The arm is dm-robotics-panda's ``panda.xml`` (Apache-2.0, shipped in ``sim/assets/panda`` with decimated
meshes; the same kinematics as the FR3, whose joint limits differ and are set here) with a closed
Franka hand built from its ``hand.stl``/``finger.stl``
meshes and the finger pad boxes of ``panda_hand.xml``, mounted ``cell.hand_yaw`` about the flange z
axis, and a ``fingertip`` site at the cell's fingertip offset. :class:`ArmKinematics` solves
damped-least-squares IK for the fingertip pointing straight down (fingers spanning the base y axis,
like the training hand) along a plan, and refuses a plan that is unreachable or brings any joint
within ``JOINT_MARGIN_RAD`` of its limit (``robot-safety.md``: IK targets ≥ 0.1 rad inside the
limits). Real executors run the same check before they send anything.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import mujoco
import numpy as np

from robot.errors import UnreachableError
from sim.scene import PANDA_ASSETS

ARM_PREFIX = "arm/"
JOINTS = tuple(f"{ARM_PREFIX}panda_joint{i}" for i in range(1, 8))
JOINT_MARGIN_RAD = 0.1  # every IK solution stays this far inside the joint limits
#: Joint limits (rad). Panda (FER) from panda.xml; FR3 from Franka's FR3 datasheet.
JOINT_LIMITS = {
    "panda": (
        np.array([-2.897, -1.7627, -2.897, -3.0717, -2.897, -0.0174, -2.897]),
        np.array([2.897, 1.7627, 2.897, -0.0698, 2.897, 3.7524, 2.897]),
    ),
    "fr3": (
        np.array([-2.7437, -1.7837, -2.9007, -3.0421, -2.8065, 0.5445, -3.0159]),
        np.array([2.7437, 1.7837, 2.9007, -0.1518, 2.8065, 4.5169, 3.0159]),
    ),
}
TORQUE_LIMITS_NM = np.array([87.0, 87.0, 87.0, 87.0, 12.0, 12.0, 12.0])  # Panda and FR3
#: Fingertip orientation in the base frame: pointing down (hand z = -z), fingers spanning y (hand
#: y = -y), i.e. a half turn about x; Franka's "ready" pose holds the hand like this.
R_DOWN = np.diag([1.0, -1.0, -1.0])
FINGER_MOUNT_M = 0.0584  # finger bodies sit this far below the flange along the hand's z axis
FINGER_PAD = dict(pos_y=0.015, pos_z=0.032, half=(0.012, 0.015, 0.022))  # panda_hand.xml's boxes
ARM_CONTYPE, ARM_CONAFFINITY = 2, 1  # collides with the scene (contype 1), never with itself
IK_TOL_POS_M = 5e-4
IK_TOL_ROT_RAD = 5e-3
PATH_STEP_M = 0.01  # IK is checked along every straight move at this spacing
NULLSPACE_GAIN = 0.05  # per IK iteration, towards the rest posture (the home pose)
MAX_JOINT_JUMP_RAD = 0.35  # a larger change between neighbouring path samples is an IK branch switch


def rot_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Unit quaternion (4,) wxyz of a rotation matrix (3, 3)."""
    q = np.empty(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(R, dtype=np.float64).ravel())
    return q


def add_arm(spec: mujoco.MjSpec, robot_type: str, fingertip_offset, hand_yaw: float, meshes: bool = True):
    """Attach the Panda/FR3 arm with a closed hand and a ``fingertip`` site to ``spec``'s world.

    The base (``arm/panda_link0``) sits at the world origin: the world frame is the robot base frame.
    Adds torque actuators ``arm/motor{1..7}`` (N·m, the arm's torque limits). Arm geoms collide with
    the scene but not with each other.
    """
    arm = mujoco.MjSpec.from_file(str(PANDA_ASSETS / "panda.xml"))
    if not meshes:  # kinematics only: no geoms, no mesh assets to compile (saves ~2 s)
        for g in list(arm.geoms):
            arm.delete(g)
        for a in [*arm.meshes, *arm.materials, *arm.textures]:
            arm.delete(a)
    frame = spec.worldbody.add_frame()
    frame.attach_body(arm.body("panda_link0"), ARM_PREFIX, "")
    lo, hi = JOINT_LIMITS["fr3" if robot_type == "fr3" else "panda"]
    for i, name in enumerate(JOINTS):
        j = spec.joint(name)
        j.range = [lo[i], hi[i]]
        j.armature = 0.1  # reflected rotor inertia, as in Menagerie's Panda; keeps torque control stiff
    flange = spec.body(f"{ARM_PREFIX}panda_link8")
    hand = flange.add_body(name="hand", quat=quat_from_matrix(rot_z(hand_yaw)), gravcomp=1)
    hand.add_geom(  # finger pads: just a hint of mass at the tip; the hand mesh carries the rest
        name="hand_inertia",
        type=mujoco.mjtGeom.mjGEOM_SPHERE,
        size=[0.01, 0, 0],
        pos=[0, 0, 0.05],
        mass=0.73,
        contype=0,
        conaffinity=0,
        group=5,
    )
    geom = dict(contype=ARM_CONTYPE, conaffinity=ARM_CONAFFINITY, group=0, rgba=[0.92, 0.92, 0.92, 1])
    if meshes:
        spec.add_mesh(name="hand_mesh", file=str(PANDA_ASSETS / "hand.stl"))
        spec.add_mesh(name="finger_mesh", file=str(PANDA_ASSETS / "finger.stl"))
        hand.add_geom(name="hand_geom", type=mujoco.mjtGeom.mjGEOM_MESH, meshname="hand_mesh", mass=0, **geom)
        for side, quat in (("left", [0, 0, 0, 1]), ("right", [1, 0, 0, 0])):
            hand.add_geom(
                name=f"finger_{side}_visual",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname="finger_mesh",
                pos=[0, 0, FINGER_MOUNT_M],
                quat=quat,
                contype=0,
                conaffinity=0,
                mass=0,
                group=0,
                rgba=[0.3, 0.3, 0.3, 1],
            )
    hx, hy, hz = FINGER_PAD["half"]
    zc = FINGER_MOUNT_M + FINGER_PAD["pos_z"]
    for side, y in (("left", -FINGER_PAD["pos_y"]), ("right", FINGER_PAD["pos_y"])):
        hand.add_geom(
            name=f"finger_{side}_pad",
            type=mujoco.mjtGeom.mjGEOM_BOX,
            size=[hx, hy, hz],
            pos=[0, y, zc],
            mass=0,
            friction=[0.8, 0.005, 0.0001],
            **{**geom, "group": 3},
        )
    offset = rot_z(hand_yaw).T @ np.asarray(fingertip_offset, dtype=np.float64)  # flange -> hand frame
    hand.add_site(name="fingertip", pos=offset, size=[0.004, 0, 0], group=4)
    for i, name in enumerate(JOINTS):
        act = spec.add_actuator(name=f"{ARM_PREFIX}motor{i + 1}", target=name)
        act.trntype = mujoco.mjtTrn.mjTRN_JOINT
        act.gainprm[0] = 1.0
        act.ctrlrange = [-TORQUE_LIMITS_NM[i], TORQUE_LIMITS_NM[i]]
        act.ctrllimited = True
    for g in spec.geoms:  # the arm's own meshes: collide with the scene only
        if g.name.startswith(ARM_PREFIX) or g.parent.name.startswith(ARM_PREFIX):
            g.contype, g.conaffinity = ARM_CONTYPE, ARM_CONAFFINITY
    return hand


def orientation_error(R: np.ndarray, R_target: np.ndarray) -> np.ndarray:
    """Rotation-vector-like error (3,) that drives ``R`` towards ``R_target`` (small-angle exact)."""
    E = R_target @ R.T  # = 0.5 Σ_i R[:, i] × R_target[:, i], without three slow np.cross calls
    return 0.5 * np.array([E[2, 1] - E[1, 2], E[0, 2] - E[2, 0], E[1, 0] - E[0, 1]])


@dataclass
class PathSolution:
    """Joint configurations along a checked path: ``q (K, 7)`` at the fingertip targets ``points (K, 3)``."""

    points: np.ndarray
    q: np.ndarray
    min_margin_rad: float  # smallest distance of any joint to its limit along the path
    labels: list[str]


class ArmKinematics:
    """Fingertip forward/inverse kinematics on an arm model (the twin's, or a kinematics-only copy).

    ``model`` must contain the arm added by :func:`add_arm`; a private ``MjData`` is used, so the
    twin's simulation state is never touched.
    """

    def __init__(self, model: mujoco.MjModel, robot_type: str = "panda", margin: float = JOINT_MARGIN_RAD):
        self.model = model
        self.data = mujoco.MjData(model)
        self.qadr = np.array([model.jnt_qposadr[model.joint(j).id] for j in JOINTS])
        self.dadr = np.array([model.jnt_dofadr[model.joint(j).id] for j in JOINTS])
        self.site = model.site("fingertip").id
        self.lo, self.hi = JOINT_LIMITS["fr3" if robot_type == "fr3" else "panda"]
        self.margin = margin
        self._jp = np.zeros((3, model.nv))
        self._jr = np.zeros((3, model.nv))

    @classmethod
    def for_cell(cls, cell) -> ArmKinematics:
        """A kinematics-only arm (no meshes, no scene) for ``cell``'s robot type and tool."""
        return cls(
            _kinematic_model(cell.robot_type, tuple(cell.fingertip_offset), cell.hand_yaw), cell.robot_type
        )

    def fk(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fingertip ``(position (3,), rotation (3, 3))`` in the base frame at joints ``q (7,)``."""
        d = self.data
        d.qpos[self.qadr] = q
        mujoco.mj_kinematics(self.model, d)
        return d.site_xpos[self.site].copy(), d.site_xmat[self.site].reshape(3, 3).copy()

    def jacobian(self, q: np.ndarray | None = None) -> np.ndarray:
        """Fingertip Jacobian (6, 7) [linear; angular] at ``q`` (or the last FK state)."""
        if q is not None:
            self.fk(q)
        mujoco.mj_comPos(self.model, self.data)
        mujoco.mj_jacSite(self.model, self.data, self._jp, self._jr, self.site)
        return np.vstack([self._jp[:, self.dadr], self._jr[:, self.dadr]])

    def ik(
        self,
        target: np.ndarray,
        q0: np.ndarray,
        R_target: np.ndarray = R_DOWN,
        q_rest: np.ndarray | None = None,
        iters: int = 100,
    ) -> tuple[np.ndarray, float, float]:
        """Damped least squares from ``q0``: returns ``(q (7,), position error m, rotation error rad)``.

        A null-space term pulls towards ``q_rest`` (default ``q0``), keeping the posture continuous.
        """
        q = np.array(q0, dtype=np.float64)
        q_rest = q if q_rest is None else np.asarray(q_rest, dtype=np.float64)
        q_rest = q_rest.copy()
        lam2 = 1e-4
        ep = er = np.zeros(3)
        for _ in range(iters):
            p, R = self.fk(q)
            ep = target - p
            er = orientation_error(R, R_target)
            if np.linalg.norm(ep) < IK_TOL_POS_M * 0.2 and np.linalg.norm(er) < IK_TOL_ROT_RAD * 0.2:
                break
            J = self.jacobian()
            e = np.concatenate([ep, er])
            JJt = J @ J.T + lam2 * np.eye(6)
            dq = J.T @ np.linalg.solve(JJt, e)
            Jpinv = J.T @ np.linalg.inv(JJt)
            dq += (np.eye(7) - Jpinv @ J) @ (NULLSPACE_GAIN * (q_rest - q))
            step = np.abs(dq).max()
            if step > 0.2:
                dq *= 0.2 / step
            q = np.clip(q + dq, self.lo, self.hi)
        p, R = self.fk(q)
        return q, float(np.linalg.norm(target - p)), float(np.linalg.norm(orientation_error(R, R_target)))

    def margin_of(self, q: np.ndarray) -> tuple[float, int]:
        """Smallest distance (rad) of ``q`` to a joint limit, and that joint's index."""
        m = np.minimum(q - self.lo, self.hi - q)
        i = int(np.argmin(m))
        return float(m[i]), i

    def solve_path(
        self, points: np.ndarray, q_start: np.ndarray, labels: list[str] | None = None
    ) -> PathSolution:
        """IK along straight fingertip moves from FK(``q_start``) through ``points (K, 3)``.

        Every move is sampled every ``PATH_STEP_M``; each sample must converge, stay
        ``self.margin`` inside the joint limits and change no joint by more than
        ``MAX_JOINT_JUMP_RAD`` from the previous sample. Raises ``UnreachableError`` naming the
        waypoint and the reason; returns the configurations at ``points``.
        """
        points = np.asarray(points, dtype=np.float64)
        labels = labels or [f"waypoint {i}" for i in range(len(points))]
        q = np.asarray(q_start, dtype=np.float64).copy()
        q_rest = q.copy()
        m0, j0 = self.margin_of(q)
        if m0 < self.margin:
            raise UnreachableError(
                f"start configuration has joint {j0 + 1} within {m0:.3f} rad of its limit "
                f"(margin {self.margin} rad): move the arm to its home pose first"
            )
        prev_p, _ = self.fk(q)
        out, min_margin = [], m0
        for k, target in enumerate(points):
            n = max(1, int(np.ceil(np.linalg.norm(target - prev_p) / PATH_STEP_M)))
            for s in range(1, n + 1):
                sample = prev_p + (target - prev_p) * (s / n)
                q_new, ep, er = self.ik(sample, q, q_rest=q_rest)
                if ep > IK_TOL_POS_M or er > IK_TOL_ROT_RAD:
                    raise UnreachableError(
                        f"{labels[k]} at {np.round(sample, 3).tolist()} m is unreachable with the hand "
                        f"pointing down (IK error {ep * 1000:.1f} mm, {np.degrees(er):.1f} deg)"
                    )
                jump = np.abs(q_new - q).max()
                if jump > MAX_JOINT_JUMP_RAD:
                    raise UnreachableError(
                        f"{labels[k]}: the move to {np.round(sample, 3).tolist()} m needs a joint jump of "
                        f"{jump:.2f} rad (an IK branch switch): refused"
                    )
                margin, j = self.margin_of(q_new)
                if margin < self.margin:
                    raise UnreachableError(
                        f"{labels[k]} at {np.round(sample, 3).tolist()} m brings joint {j + 1} within "
                        f"{margin:.3f} rad of its limit (margin {self.margin} rad)"
                    )
                min_margin = min(min_margin, margin)
                q = q_new
            prev_p = target
            out.append(q.copy())
        return PathSolution(points, np.array(out), min_margin, labels)


@functools.lru_cache(maxsize=4)
def _kinematic_model(robot_type: str, fingertip_offset: tuple, hand_yaw: float) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    add_arm(spec, robot_type, fingertip_offset, hand_yaw, meshes=False)
    return spec.compile()
