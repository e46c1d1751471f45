"""The MuJoCo twin of a cell: the Franka arm, the bin, the object and the cell's depth cameras.

:class:`TwinWorld` builds the scene from the cell file (world frame = robot base frame): the arm of
``robot.arm`` (dm-robotics-panda's Panda with a closed hand, torque actuators) at the origin, the
bin's floor and walls at ``bin.center_m``, the object as a free body of convex parts (the training
scene's physics, ``sim.scene``), and one MuJoCo camera per cell camera at its calibrated pose and
field of view. Time step 4 ms: tracking and contact forces match a 2 ms run (the object's training physics uses 5 ms).

:class:`TwinExecutor` drives the arm like panda-python's Cartesian impedance controller: a
translational spring ``limits.cartesian_stiffness_npm`` and a rotational one on the fingertip
(pointing down), critically damped, with a null-space spring towards the IK solution of the target,
the reference moving along each straight move at the command's speed. Like libfranka's torque interface,
it commands torques with gravity and joint friction compensated (the arm model's ``frictionloss`` is
zeroed), so the fingertip tracks the waypoints to ~2 mm. Every physics step it measures
the contact force on the arm: above ``force_stop_n`` the move is stopped (``reaction_fired``), above
``collision_force_n`` the twin latches a ``cartesian_reflex`` like the real robot, until ``recover``.
Either way the arm then holds still for a moment (the real arm stops; a recovery takes longer), so the
retract that follows does not start inside the contact's transient.

:class:`TwinCamera` renders depth (geom groups 0-1: bin, object, arm, table) with Gaussian noise, the way a
RealSense frame arrives, and :meth:`TwinWorld.true_mask` gives the ground-truth object mask.
"""

from __future__ import annotations

import os
import time

os.environ.setdefault("MUJOCO_GL", "egl")  # offscreen rendering; must precede the first mujoco import

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from robot.arm import JOINTS, R_DOWN, ArmKinematics, add_arm, orientation_error  # noqa: E402
from robot.cameras import Camera, Frame  # noqa: E402
from robot.executor import Command, Executor, MoveResult, Outcome, RobotMode  # noqa: E402
from sim.contract import pose_matrix  # noqa: E402
from sim.goals import sample_episode as sim_sample_episode  # noqa: E402
from sim.objects import ObjectAsset  # noqa: E402
from sim.scene import add_object_body  # noqa: E402  (the training scene's object body: one definition)

TIMESTEP_S = 0.004
WALL_THICKNESS_M = 0.01
FLOOR_THICKNESS_M = 0.02
EFFECTIVE_MASS_KG = 2.0  # for critical damping of the translational spring
EFFECTIVE_INERTIA_KGM2 = 0.05  # ... and of the rotational one
NULLSPACE_STIFFNESS = 10.0  # N·m/rad towards the IK posture
NULLSPACE_DAMPING = 3.0  # N·m·s/rad
JOINT_DAMPING = 0.5  # N·m·s/rad on every joint, on top of the model's own
SETTLE_TOL_M = 0.002  # a move has arrived when the fingertip is this close to its target ...
SETTLE_MAX_S = 1.0  # ... or after this long once the reference has arrived
CONTACT_SETTLE_S = 0.2  # (contact and push moves end against the object: do not wait long)
FORCE_STOP_HOLD_S = 0.1  # after a force stop the arm holds still this long
REFLEX_HOLD_S = 0.1  # ... and after a reflex (the robot stops and holds in reflex mode until recover())
OBJECT_SETTLE_MAX_S = 1.5
FAR_AWAY = np.array([0.0, 0.0, 20.0])  # where the object goes for an empty-bin (background) render
MAX_RANGE_M = 6.0  # depth beyond this is reported as a hole (0), like a RealSense out of range


class TwinWorld:
    """The twin's scene and physics. One model per object (cached); the arm starts at home."""

    def __init__(
        self, cell, robot_type: str = "panda", seed: int | None = 0, depth_noise: float | None = None
    ):
        self.cell = cell
        self.robot_type = robot_type
        self.rng = np.random.default_rng(seed)
        self.depth_noise = cell.twin_depth_noise if depth_noise is None else depth_noise
        self._models: dict[str, mujoco.MjModel] = {}
        self._renderers: dict[tuple[int, int], mujoco.Renderer] = {}
        self.asset: ObjectAsset | None = None
        self.model: mujoco.MjModel | None = None
        self.data: mujoco.MjData | None = None
        # controller state
        self.x_ref = np.zeros(3)
        self.v_ref = np.zeros(3)  # reference velocity (m/s): damping acts on the tracking error
        self.q_ref = np.array(cell.home_joints, dtype=np.float64)
        self.mode = RobotMode.idle
        self.errors: tuple[str, ...] = ()
        self.latched_reflex = False  # test hook: the mode stays in reflex after the first recover()

    # --- model -------------------------------------------------------------------------------------
    def _build(self, asset: ObjectAsset) -> mujoco.MjModel:
        cell = self.cell
        spec = mujoco.MjSpec()
        spec.compiler.degree = False
        spec.option.timestep = TIMESTEP_S
        spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
        spec.option.cone = mujoco.mjtCone.mjCONE_PYRAMIDAL
        spec.visual.global_.offwidth = max(640, *(c.width for c in cell.cameras))
        spec.visual.global_.offheight = max(480, *(c.height for c in cell.cameras))
        wb = spec.worldbody
        wb.add_light(name="top", pos=[cell.bin_center[0], 0, 1.5], dir=[0, 0, -1], diffuse=[0.8, 0.8, 0.8])
        floor_z = cell.floor_z
        wb.add_geom(  # the table under the bin: seen by the depth cameras (as a real camera sees it)
            name="ground",
            type=mujoco.mjtGeom.mjGEOM_PLANE,
            pos=[cell.bin_center[0], cell.bin_center[1], floor_z - FLOOR_THICKNESS_M],
            size=[1.5, 1.5, 0.01],
            contype=0,
            conaffinity=0,
            group=1,
            rgba=[0.3, 0.3, 0.32, 1],
        )
        hx, hy, h = cell.bin_size[0] / 2, cell.bin_size[1] / 2, cell.bin_size[2]
        t = WALL_THICKNESS_M / 2
        binb = wb.add_body(name="bin", pos=cell.bin_center.tolist())
        box = dict(
            type=mujoco.mjtGeom.mjGEOM_BOX, group=0, rgba=[0.55, 0.45, 0.35, 1], friction=[0.5, 0.005, 0.0001]
        )
        binb.add_geom(
            name="bin_floor",
            pos=[0, 0, -FLOOR_THICKNESS_M / 2],
            size=[hx + 2 * t, hy + 2 * t, FLOOR_THICKNESS_M / 2],
            **box,
        )
        binb.add_geom(name="bin_wall_xpos", pos=[hx + t, 0, h / 2], size=[t, hy + 2 * t, h / 2], **box)
        binb.add_geom(name="bin_wall_xneg", pos=[-hx - t, 0, h / 2], size=[t, hy + 2 * t, h / 2], **box)
        binb.add_geom(name="bin_wall_ypos", pos=[0, hy + t, h / 2], size=[hx + 2 * t, t, h / 2], **box)
        binb.add_geom(name="bin_wall_yneg", pos=[0, -hy - t, h / 2], size=[hx + 2 * t, t, h / 2], **box)
        add_arm(spec, self.robot_type, cell.fingertip_offset, cell.hand_yaw)
        add_object_body(spec, "object", asset, rgba=[0.85, 0.35, 0.2, 1.0])
        weld = spec.add_equality(name="object_weld")
        weld.type = mujoco.mjtEq.mjEQ_WELD
        weld.objtype = mujoco.mjtObj.mjOBJ_BODY
        weld.name1 = "object"
        weld.active = False
        for i, cam in enumerate(cell.cameras):
            R_mj = cam.T_base_camera[:3, :3] @ np.diag([1.0, -1.0, -1.0])  # OpenCV optical -> MuJoCo
            q = np.empty(4)
            mujoco.mju_mat2Quat(q, np.ascontiguousarray(R_mj).ravel())
            fovy = float(np.degrees(2 * np.arctan2(cam.height / 2, cam.K[1, 1])))
            wb.add_camera(name=f"cam{i}", pos=cam.T_base_camera[:3, 3].tolist(), quat=q.tolist(), fovy=fovy)
        model = spec.compile()
        arm_dofs = [model.jnt_dofadr[model.joint(j).id] for j in JOINTS]
        model.dof_damping[arm_dofs] += JOINT_DAMPING
        # libfranka's torque commands are "without gravity and friction": the robot compensates both
        # (gravity here by ``gravcomp``). dm-robotics-panda's joint Coulomb friction (up to 1.2 N·m on
        # joint 7) left uncompensated made every move stop 3-9 mm from its target under the 500 N/m
        # spring, so the twin's fingertip did not follow the primitive's waypoints.
        model.dof_frictionloss[arm_dofs] = 0.0
        return model

    def load(self, asset: ObjectAsset) -> None:
        """Switch to ``asset`` (building its model once); resets all state, arm at home."""
        if asset.name not in self._models:
            self._models[asset.name] = self._build(asset)
        model = self._models[asset.name]
        if model is not self.model:
            for r in self._renderers.values():
                r.close()
            self._renderers.clear()
        self.asset, self.model = asset, model
        self.data = mujoco.MjData(model)
        m = model
        self.qadr = np.array([m.jnt_qposadr[m.joint(j).id] for j in JOINTS])
        self.dadr = np.array([m.jnt_dofadr[m.joint(j).id] for j in JOINTS])
        self.act = np.array([m.actuator(f"arm/motor{i}").id for i in range(1, 8)])
        self.site = m.site("fingertip").id
        self.obj_body = m.body("object").id
        self.obj_qadr = m.jnt_qposadr[m.joint("object_joint").id]
        self.obj_dadr = m.jnt_dofadr[m.joint("object_joint").id]
        self.weld_id = m.equality("object_weld").id
        self.arm_geoms = np.flatnonzero(
            np.isin(m.geom_bodyid, [b for b in range(m.nbody) if self._is_arm_body(b)])
        )
        self._arm_geom_mask = np.zeros(m.ngeom, dtype=bool)
        self._arm_geom_mask[self.arm_geoms] = True
        self.obj_geoms = np.flatnonzero(m.geom_bodyid == self.obj_body)
        self.kin = ArmKinematics(m, self.robot_type)
        if not (
            np.all(np.diff(self.qadr) == 1)
            and np.all(np.diff(self.dadr) == 1)
            and np.all(np.diff(self.act) == 1)
        ):
            raise RuntimeError("the twin expects the arm's joints and motors to be contiguous")
        self._q0, self._dof0, self._act0 = int(self.qadr[0]), int(self.dadr[0]), int(self.act[0])
        self._jac = np.zeros((6, m.nv))
        self._wrench = np.zeros(6)
        lim = self.cell.limits
        self._k, self._kr = lim.cartesian_stiffness, lim.rotational_stiffness
        self._dk = 2 * np.sqrt(self._k * EFFECTIVE_MASS_KG)
        self._dkr = 2 * np.sqrt(self._kr * EFFECTIVE_INERTIA_KGM2)
        self.reset_arm()
        self.hide_object()

    def _is_arm_body(self, b: int) -> bool:
        name = self.model.body(b).name
        return name.startswith("arm/") or name == "hand"

    def close(self) -> None:
        for r in self._renderers.values():
            r.close()
        self._renderers.clear()

    # --- state -------------------------------------------------------------------------------------
    def reset_arm(self, q: np.ndarray | None = None) -> None:
        """Teleport the arm to ``q`` (default home) at rest; reference there; mode idle."""
        q = np.array(self.cell.home_joints if q is None else q, dtype=np.float64)
        self.data.qpos[self.qadr] = q
        self.data.qvel[self.dadr] = 0.0
        self.data.ctrl[:] = 0.0
        mujoco.mj_forward(self.model, self.data)
        self.x_ref = self.fingertip()
        self.v_ref = np.zeros(3)
        self.q_ref = q.copy()
        self.mode, self.errors = RobotMode.idle, ()

    def fingertip(self) -> np.ndarray:
        return self.data.site_xpos[self.site].copy()

    def joints(self) -> np.ndarray:
        return self.data.qpos[self.qadr].copy()

    def set_object_pose(self, pos, quat_wxyz) -> None:
        """Place the object (base frame) at rest."""
        a = self.obj_qadr
        self.data.qpos[a : a + 3] = pos
        self.data.qpos[a + 3 : a + 7] = np.asarray(quat_wxyz) / np.linalg.norm(quat_wxyz)
        self.data.qvel[self.obj_dadr : self.obj_dadr + 6] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def object_pose(self) -> tuple[np.ndarray, np.ndarray]:
        q = self.data.qpos[self.obj_qadr : self.obj_qadr + 7]
        return q[:3].copy(), q[3:].copy()

    def object_T(self) -> np.ndarray:
        """Pose (4, 4) of the object in the base frame."""
        return pose_matrix(*self.object_pose())

    def hide_object(self) -> None:
        """Move the object far above every view (for empty-bin background captures)."""
        self.set_object_pose(FAR_AWAY, [1.0, 0.0, 0.0, 0.0])

    def weld_object(self, on: bool) -> None:
        """Weld the object to the world where it is (fault tests: a push that cannot move it)."""
        m, d = self.model, self.data
        if on:
            T = self.object_T()
            inv = np.linalg.inv(T)  # the world's pose in the object's frame
            q = np.empty(4)
            mujoco.mju_mat2Quat(q, np.ascontiguousarray(inv[:3, :3]).ravel())
            m.eq_data[self.weld_id, :3] = 0.0  # anchor
            m.eq_data[self.weld_id, 3:6] = inv[:3, 3]
            m.eq_data[self.weld_id, 6:10] = q
            m.eq_data[self.weld_id, 10] = 1.0  # torque scale
        d.eq_active[self.weld_id] = int(on)

    def object_in_bin(self) -> bool:
        """False once the object's origin left the bin's inner volume (2 cm margin), as in training."""
        pos, _ = self.object_pose()
        rel = pos - self.cell.bin_center
        half = self.cell.bin_size[:2] / 2 + 0.02
        return bool(np.all(np.abs(rel[:2]) < half) and -0.02 < rel[2] < 0.35)

    def object_speed(self) -> float:
        v = self.data.qvel[self.obj_dadr : self.obj_dadr + 6]
        return float(max(np.linalg.norm(v[:3]), 0.1 * np.linalg.norm(v[3:])))

    # --- physics with the arm's controller -----------------------------------------------------------
    def _control(self) -> None:
        """Cartesian impedance + null-space posture spring; gravity is compensated by ``gravcomp``."""
        m, d = self.model, self.data
        a0 = self._dof0  # the arm's 7 dofs are contiguous: slices, not fancy indexing (hot loop)
        q, qd = d.qpos[self._q0 : self._q0 + 7], d.qvel[a0 : a0 + 7]
        mujoco.mj_jacSite(m, d, self._jac[:3], self._jac[3:], self.site)
        J = self._jac[:, a0 : a0 + 7]  # (6, 7)
        p = d.site_xpos[self.site]
        R = d.site_xmat[self.site].reshape(3, 3)
        v = J @ qd  # (6,) fingertip twist
        wrench = self._wrench
        wrench[:3] = self._k * (self.x_ref - p) + self._dk * (self.v_ref - v[:3])
        wrench[3:] = self._kr * orientation_error(R, R_DOWN) - self._dkr * v[3:]
        JJt = J @ J.T
        JJt.flat[::7] += 1e-4
        # null-space projector I - J^T (J J^T)^-1 J, applied to the posture torque
        tau_null = NULLSPACE_STIFFNESS * (self.q_ref - q) - NULLSPACE_DAMPING * qd
        tau_null -= J.T @ np.linalg.solve(JJt, J @ tau_null)
        d.ctrl[self._act0 : self._act0 + 7] = J.T @ wrench + tau_null

    def contact_force(self) -> float:
        """|net contact force| (N) on the arm and hand from everything else (bin, object)."""
        m, d = self.model, self.data
        if d.ncon == 0:
            return 0.0
        geoms = d.contact.geom
        on1 = self._arm_geom_mask[geoms[:, 0]]
        on2 = self._arm_geom_mask[geoms[:, 1]]
        touching = on1 ^ on2
        if not touching.any():
            return 0.0
        total = np.zeros(3)
        f6 = np.zeros(6)
        frames = d.contact.frame
        for i in np.flatnonzero(touching):
            mujoco.mj_contactForce(m, d, int(i), f6)
            f = frames[i].reshape(3, 3).T @ f6[:3]  # force on geom2, world frame
            total += f if on2[i] else -f
        return float(np.linalg.norm(total))

    def step(self) -> float:
        """One controlled physics step; returns the arm's contact force (N) after it."""
        m, d = self.model, self.data
        mujoco.mj_step1(m, d)
        self._control()
        mujoco.mj_step2(m, d)
        return self.contact_force()

    def settle_object(self, max_s: float = OBJECT_SETTLE_MAX_S) -> None:
        """Step (arm holding) until the object is at rest, at most ``max_s``."""
        calm = 0
        for _ in range(int(max_s / TIMESTEP_S)):
            self.step()
            calm = calm + 1 if self.object_speed() < 0.005 else 0
            if calm >= 10:
                break

    def place_object(self, pos, quat_wxyz) -> np.ndarray:
        """Put the object at ``pos`` (m, base frame), ``quat_wxyz`` and let it settle; returns the
        pose (4, 4) it came to rest at (an episode's start or goal as the cameras will see it)."""
        self.set_object_pose(pos, quat_wxyz)
        self.settle_object()
        return self.object_T()

    # --- rendering ---------------------------------------------------------------------------------
    def _renderer(self, height: int, width: int) -> mujoco.Renderer:
        key = (height, width)
        if key not in self._renderers:
            self._renderers[key] = mujoco.Renderer(self.model, height, width)
        return self._renderers[key]

    @staticmethod
    def _option() -> mujoco.MjvOption:
        opt = mujoco.MjvOption()
        opt.geomgroup[:] = 0
        opt.geomgroup[:2] = 1  # bin, object, arm meshes, table; not the finger pads (3) or sites
        opt.sitegroup[:] = 0
        return opt

    def render_depth(self, cam_index: int) -> np.ndarray:
        """Noise-free z-depth (H, W) float32 metres of cell camera ``cam_index``."""
        spec = self.cell.cameras[cam_index]
        r = self._renderer(spec.height, spec.width)
        r.enable_depth_rendering()
        r.update_scene(self.data, f"cam{cam_index}", self._option())
        depth = r.render().astype(np.float32)
        r.disable_depth_rendering()
        return depth

    def true_mask(self, cam_index: int, bodies: str = "object") -> np.ndarray:
        """Ground truth (H, W) bool: pixels showing the object (or ``bodies="arm"``: the arm)."""
        spec = self.cell.cameras[cam_index]
        r = self._renderer(spec.height, spec.width)
        r.enable_segmentation_rendering()
        r.update_scene(self.data, f"cam{cam_index}", self._option())
        seg = r.render()
        r.disable_segmentation_rendering()
        geoms = self.obj_geoms if bodies == "object" else self.arm_geoms
        return (seg[..., 1] == int(mujoco.mjtObj.mjOBJ_GEOM)) & np.isin(seg[..., 0], geoms)


class TwinCamera(Camera):
    """A cell camera rendered in the twin: depth + Gaussian noise (the world's ``depth_noise``)."""

    kind = "twin"

    def __init__(self, world: TwinWorld, spec, index: int):
        super().__init__(spec)
        self.world, self.index = world, index
        self._count = 0
        self._open = False

    def open(self) -> None:
        if self.world is None or self.world.model is None:
            raise RuntimeError("the twin world has no scene loaded")
        self._open = True

    def close(self) -> None:
        self._open = False

    def capture(self) -> Frame:
        depth = self.world.render_depth(self.index)
        if self.world.depth_noise > 0:
            depth = depth + self.world.depth_noise * self.world.rng.standard_normal(
                depth.shape, dtype=np.float32
            )
        depth[depth > MAX_RANGE_M] = 0.0  # nothing hit (the far plane): a hole, as a RealSense reports it
        self._count += 1
        return Frame(self.spec.serial, depth, time.time(), self._count)


class TwinExecutor(Executor):
    """The executor contract on the twin's arm (see the module docstring for the controller)."""

    name = "sim"

    def __init__(self, world: TwinWorld, cell, log=None, speed_scale: float = 1.0):
        super().__init__(cell, log, speed_scale)
        self.world = world

    def connect(self) -> None:
        if self.world.model is None:
            raise RuntimeError("the twin world has no scene loaded")

    def disconnect(self) -> None:
        pass

    def stop(self) -> None:
        w = self.world
        if w.model is not None:
            w.x_ref = w.fingertip()
            w.v_ref = np.zeros(3)
            w.q_ref = w.joints()

    def recover(self) -> None:
        w = self.world
        if w.latched_reflex:  # the latched-mode variant: flags clear, the mode stays in reflex once
            w.latched_reflex = False
            w.errors = ()
            return
        w.mode, w.errors = RobotMode.idle, ()
        self.stop()

    def robot_mode(self) -> RobotMode:
        return self.world.mode

    def current_errors(self) -> tuple[str, ...]:
        return self.world.errors

    def fingertip(self) -> np.ndarray:
        return self.world.fingertip()

    def joints(self) -> np.ndarray:
        return self.world.joints()

    def _hold(self, seconds: float) -> float:
        peak = 0.0
        for _ in range(int(seconds / TIMESTEP_S)):
            peak = max(peak, self.world.step())
        return peak

    def _move(self, command: Command) -> MoveResult:
        w, lim = self.world, self.cell.limits
        if w.mode is not RobotMode.idle:  # libfranka refuses motions while in reflex
            return MoveResult(
                Outcome.reflex,
                w.fingertip(),
                0.0,
                w.errors or ("cartesian_reflex",),
                "robot is in reflex mode",
            )
        target = np.asarray(command.target, dtype=np.float64)
        if command.kind == "home":
            q_goal = np.array(self.cell.home_joints, dtype=np.float64)
        else:
            q_goal, _, _ = w.kin.ik(target, w.joints(), q_rest=w.q_ref)
        start, q_start = w.x_ref.copy(), w.q_ref.copy()
        n = max(1, int(np.ceil(np.linalg.norm(target - start) / (command.speed * TIMESTEP_S))))
        deadline = lim.motion_timeout / TIMESTEP_S
        peak, steps = 0.0, 0
        settle_steps = int((CONTACT_SETTLE_S if command.in_contact else SETTLE_MAX_S) / TIMESTEP_S)
        v_move = (target - start) / (n * TIMESTEP_S)
        for s in range(1, n + 1 + settle_steps):
            a = min(1.0, s / n)
            w.x_ref = start + (target - start) * a
            w.v_ref = v_move if s <= n else np.zeros(3)
            w.q_ref = q_start + (q_goal - q_start) * a
            f = w.step()
            steps += 1
            peak = max(peak, f)
            if f > lim.collision_force:  # the robot's own reflex: latched until recover()
                w.mode, w.errors = RobotMode.reflex, ("cartesian_reflex",)
                self.stop()
                peak = max(peak, self._hold(REFLEX_HOLD_S))
                return MoveResult(Outcome.reflex, w.fingertip(), peak, w.errors, f"contact force {f:.1f} N")
            if f > lim.force_stop:  # hydo's contact-force stop: stop here, no robot error
                self.stop()
                peak = max(peak, self._hold(FORCE_STOP_HOLD_S))
                return MoveResult(
                    Outcome.reaction_fired,
                    w.fingertip(),
                    peak,
                    (),
                    f"contact force {f:.1f} N > {lim.force_stop:g} N",
                )
            if steps > deadline:
                self.stop()
                return MoveResult(Outcome.short_of_goal, w.fingertip(), peak, (), "motion deadline passed")
            if s >= n and np.linalg.norm(w.fingertip() - target) < SETTLE_TOL_M:
                break
        err = float(np.linalg.norm(w.fingertip() - target))
        if err > lim.position_tolerance and not command.in_contact:
            self.stop()
            return MoveResult(
                Outcome.short_of_goal, w.fingertip(), peak, (), f"stopped {err * 1000:.0f} mm short"
            )
        return MoveResult(Outcome.ok, w.fingertip(), peak)


def sample_episode(world: TwinWorld, assets, goal_mode: str, rng: np.random.Generator):
    """A start and a goal like the training env's ``reset`` (``sim.env.BinEnv``), in the base frame.

    Returns ``(asset, (start_pos, start_quat), (goal_pos, goal_quat))``: the training env's episode
    (``sim.goals.sample_episode``: a random object, one of its stable poses at a random yaw and bin
    position, a ``planar`` or ``6d`` goal at least ``MIN_GOAL_DISTANCE_M`` away) moved from the bin
    frame to the cell's bin.
    """
    asset, (pos, quat), (gpos, gquat) = sim_sample_episode(assets, goal_mode, rng)
    offset = world.cell.bin_center
    return asset, (pos + offset, quat), (gpos + offset, gquat)
