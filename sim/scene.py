"""The native MuJoCo bin scene: bin + floating Panda hand + one object (+ clutter), and the primitive's
execution in it.

``assets/scene.xml`` includes ``bin.xml`` and ``hand.xml``; this module adds the object as a free body
of convex mesh parts, optional clutter bodies, a translucent goal ghost (a mocap body, group 4,
never collides) and the Panda hand meshes as visuals.

Frames and units: world frame, metres, quaternions wxyz. The bin floor's top is z = 0.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
from mujoco import rollout

from sim.contract import CONTACT_MODELS, pose_matrix, transform_points
from sim.objects import ObjectAsset
from sim.primitive import BIN_INNER_SIZE_M, FORCE_STOP_N, PUSH_SEGMENTS

ASSETS = Path(__file__).parent / "assets"
#: The Panda arm and hand (``panda.xml``, ``hand.stl``, ``finger.stl``...), shipped with the package:
#: dm-robotics-panda 0.4.8's model with decimated meshes (``assets/panda/NOTICE``). The scene's hand
#: visuals and ``robot.arm``'s arm (the deploy twin and every executor's plan check) load it from here.
PANDA_ASSETS = ASSETS / "panda"
# What get_state/set_state carry: MuJoCo's full integration state. qpos/qvel/ctrl alone leave out the
# solver's warm start, and a push replayed from such a state ended up to 6.6 cm elsewhere.
_FULL_STATE = mujoco.mjtState.mjSTATE_INTEGRATION
# A primitive's open-loop stretch runs in one ``mujoco.rollout`` call (no Python per physics step):
# from the physics state and warm start, with the user inputs (controls, mocap poses, applied forces)
# set at every step, the same mj_step calls as a Python loop that sets ``ctrl``, bit for bit.
_PHYSICS_STATE = mujoco.mjtState.mjSTATE_FULLPHYSICS
_USER_STATE = mujoco.mjtState.mjSTATE_USER  # ctrl comes first in it
PARK_POS = np.array([0.0, 0.0, 1.5])  # hand parked far above the bin, outside every camera's view

OBJECT_DENSITY = 400.0  # kg/m^3, light wood/plastic: a 10 cm object weighs 0.1-0.4 kg
OBJECT_FRICTION = (0.5, 0.005, 0.0001)  # sliding, torsional, rolling
APPROACH_SPEED = 0.2  # m/s, fingertip speed from pre-contact to contact
PUSH_SPEED = 0.15  # m/s, fingertip speed while pushing
TRACK_STEPS = 10  # physics steps (50 ms) to let the actuators converge after each push target
START_PENETRATION_M = 0.003  # a teleported start deeper than this inside something is refused
SETTLE_MAX_S = 1.5  # cap on waiting for the object to come to rest
SETTLE_LIN_VEL = 0.005  # m/s: at rest below this ...
SETTLE_ANG_VEL = 0.05  # rad/s: ... and this


def _at_rest(v: list[float]) -> bool:
    """Whether every free body with velocities ``v`` (6 per body: linear, angular) is at rest: the
    norms in np.linalg.norm's order (Python floats: the same IEEE operations, without numpy's
    per-call overhead on a few numbers)."""
    for i in range(0, len(v), 6):
        a, b, c, x, y, z = v[i : i + 6]
        if not (math.sqrt(a * a + b * b + c * c) < SETTLE_LIN_VEL):
            return False
        if not (math.sqrt(x * x + y * y + z * z) < SETTLE_ANG_VEL):
            return False
    return True


def push_controls(waypoints: np.ndarray, timestep: float) -> np.ndarray:
    """The hand's position targets ``(T, 3)``, one per physics step, from the pre-contact waypoint
    ``waypoints[0]`` (where the hand starts) through the pushes (each followed by ``TRACK_STEPS`` at
    its end) to the retract lift ``waypoints[-1]``: straight lines at ``APPROACH_SPEED`` or
    ``PUSH_SPEED``, the target interpolated at each step (``start + (end - start) · s / n``)."""
    moves = np.diff(waypoints, axis=0)  # segment i + 1 runs from waypoint i by moves[i]
    n, hold = [], []
    for i, move in enumerate(moves, start=1):  # the last: the 6 cm lift off the object
        speed = PUSH_SPEED if i in PUSH_SEGMENTS else APPROACH_SPEED
        n.append(max(1, math.ceil(math.sqrt(move.dot(move)) / (speed * timestep))))  # np.linalg.norm's
        hold.append(TRACK_STEPS if i in PUSH_SEGMENTS else 0)
    n = np.array(n)
    count = n + hold
    seg = np.repeat(np.arange(len(n)), count)  # the segment of each physics step
    s = np.arange(len(seg)) - (np.cumsum(count) - count)[seg] + 1  # its step in the segment, 1-based
    s = np.minimum(s, n[seg])  # a push's end held for TRACK_STEPS
    return waypoints[:-1][seg] + moves[seg] * (s / n[seg])[:, None]


@dataclass
class PrimitiveResult:
    """What happened when a primitive ran: ``executed`` False means the scene was left unchanged."""

    executed: bool
    reason: str = ""  # why it was not executed
    physics_steps: int = 0
    force_stopped: bool = False  # the contact force passed the stop: the hand let go there


def _add_hand_visuals(spec: mujoco.MjSpec) -> None:
    if os.environ.get("HYDO_NO_HAND_MESH"):
        return
    hand = spec.body("hand")
    spec.add_mesh(name="panda_hand_mesh", file=str(PANDA_ASSETS / "hand.stl"))
    spec.add_mesh(name="panda_finger_mesh", file=str(PANDA_ASSETS / "finger.stl"))
    rgba = [0.95, 0.95, 0.95, 1.0]
    # Wrist frame: 0.1124 m above the fingertip, rotated 180 deg about x so the fingers point down.
    flip = [0.0, 1.0, 0.0, 0.0]
    vis = dict(type=mujoco.mjtGeom.mjGEOM_MESH, contype=0, conaffinity=0, group=2, rgba=rgba)
    hand.add_geom(name="hand_visual", meshname="panda_hand_mesh", pos=[0, 0, 0.1124], quat=flip, **vis)
    # Finger meshes at 0.0584 m below the wrist; the left one is turned 180 deg about the wrist z axis.
    hand.add_geom(name="finger_r_visual", meshname="panda_finger_mesh", pos=[0, 0, 0.054], quat=flip, **vis)
    hand.add_geom(
        name="finger_l_visual", meshname="panda_finger_mesh", pos=[0, 0, 0.054], quat=[0, 0, 1, 0], **vis
    )


def add_object_body(spec, prefix: str, asset: ObjectAsset, rgba, mocap=False) -> None:
    """Add ``asset`` as a body named ``prefix`` with one mesh geom per convex part.

    The object's physics (density, friction, convex parts; geom group 0) as the training scene builds
    it: the deploy twin (``robot.twin``) adds its object with this function too. ``mocap=True`` makes
    the goal ghost instead (group 4, no collisions, no mass); otherwise the body gets a free joint
    ``{prefix}_joint``. The body starts at ``(0, 0, -1)``: place it with the scene's pose setters.
    """
    body = spec.worldbody.add_body(name=prefix, pos=[0, 0, -1.0], mocap=mocap)
    if not mocap:
        body.add_freejoint(name=f"{prefix}_joint")
    for k, verts in enumerate(asset.parts):
        mesh = f"{prefix}_part{k}"
        spec.add_mesh(name=mesh, uservert=np.asarray(verts, dtype=np.float64).ravel().tolist())
        if mocap:  # the goal ghost: drawn (group 4) but never collides and has no mass
            body.add_geom(
                name=f"{prefix}_geom{k}",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=mesh,
                contype=0,
                conaffinity=0,
                group=4,
                rgba=rgba,
            )
        else:
            body.add_geom(
                name=f"{prefix}_geom{k}",
                type=mujoco.mjtGeom.mjGEOM_MESH,
                meshname=mesh,
                density=OBJECT_DENSITY,
                friction=list(OBJECT_FRICTION),
                rgba=rgba,
                group=0,
            )


def _add_obstacle_body(spec, name: str, obstacle) -> None:
    """A static box (``sim.tasks.Obstacle``: ``centre``, ``half_size``) welded to the world, group 0."""
    body = spec.worldbody.add_body(name=name, pos=list(obstacle.centre))
    body.add_geom(
        name=f"{name}_geom",
        type=mujoco.mjtGeom.mjGEOM_BOX,
        size=list(obstacle.half_size),
        friction=list(OBJECT_FRICTION),
        rgba=[0.95, 0.95, 0.95, 1.0],
        group=0,
    )


# The training scene's contact models (``sim.contract.CONTACT_MODELS``: ``BinScene(contacts=...)``,
# ``BinEnv``, ``TrainConfig.contacts``). ``hydo``: this scene's own (the values above and in the asset
# XMLs). ``hacman``: the contact settings of HACMan's bin env (HACMan-2023/HACMan ``bin_env`` and its
# robosuite fork), the simulator the paper's figures come from: elliptic friction cones, impratio 20
# and 20 no-slip iterations; fingertip friction (3, 0.015, 0.0003); objects at 50 kg/m^3 with friction
# (0.95, 0.3, 0.1) and condim 4 (torsional friction); the bin's geoms at priority 1 and condim 4 (so
# object-bin contacts keep the bin's 0.5); the palm does not collide (robosuite's
# ``transparent_gripper_base``). Not taken over: its 2 ms step, solref / solimp, wall planes without a
# top, and its OSC hand (motion targets relative to where the hand is): the primitive and its geometry
# stay ``sim.primitive``'s. The one-step search flips twice as often in it (docs/results.md).
HACMAN_FINGER_FRICTION = (3.0, 0.015, 0.0003)
HACMAN_OBJECT_FRICTION = (0.95, 0.3, 0.1)
HACMAN_OBJECT_DENSITY = 50.0  # kg/m^3


def _hacman_contacts(spec: mujoco.MjSpec) -> None:
    """Switch a built training-scene spec to HACMan's contact settings (``CONTACT_MODELS``)."""
    spec.option.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    spec.option.impratio = 20.0
    spec.option.noslip_iterations = 20
    for g in spec.geoms:
        if g.name.startswith("bin_"):
            g.condim, g.priority = 4, 1
        elif g.name == "hand_fingers":
            g.friction = list(HACMAN_FINGER_FRICTION)
        elif g.name == "hand_palm":
            g.contype = g.conaffinity = 0
        elif g.name.startswith(("object_geom", "clutter")) and g.contype:
            g.friction, g.condim, g.density = list(HACMAN_OBJECT_FRICTION), 4, HACMAN_OBJECT_DENSITY


def build_model(
    asset: ObjectAsset,
    clutter: tuple[ObjectAsset, ...] = (),
    obstacles: tuple = (),
    contacts: str = "hydo",
) -> mujoco.MjModel:
    """Compile bin + hand + ``asset`` (body ``object``) + clutter (bodies ``clutter{i}``) + static
    obstacles (bodies ``obstacle{i}``, ``sim.tasks``) + goal ghost, with contact model ``contacts``
    (``CONTACT_MODELS``)."""
    if contacts not in CONTACT_MODELS:
        raise ValueError(f"`contacts` must be one of {list(CONTACT_MODELS)}. Got {contacts!r}.")
    spec = mujoco.MjSpec.from_file(str(ASSETS / "scene.xml"))
    _add_hand_visuals(spec)
    add_object_body(spec, "object", asset, rgba=[0.85, 0.35, 0.2, 1.0])
    for i, c in enumerate(clutter):
        add_object_body(spec, f"clutter{i}", c, rgba=[0.35, 0.25, 0.15, 1.0])
    for i, ob in enumerate(obstacles):
        _add_obstacle_body(spec, f"obstacle{i}", ob)
    add_object_body(spec, "goal", asset, rgba=[0.2, 0.8, 0.3, 0.35], mocap=True)
    if contacts == "hacman":
        _hacman_contacts(spec)
    return spec.compile()


class BinScene:
    """A compiled scene with named accessors and the primitive executor.

    Used by the gymnasium env (training, eval), goal generation and the deploy twin's object.
    """

    def __init__(
        self,
        asset: ObjectAsset,
        clutter: tuple[ObjectAsset, ...] = (),
        obstacles: tuple = (),
        force_stop_n: float | None = FORCE_STOP_N,
        contacts: str = "hydo",
    ):
        self.asset = asset
        self.contacts = contacts  # CONTACT_MODELS
        self.force_stop_n = force_stop_n  # N; None: the hand pushes up to its actuator limits
        self.clutter = clutter
        self.obstacles = tuple(obstacles)  # static boxes of a task (``sim.tasks.Obstacle``)
        self.model = build_model(asset, clutter, self.obstacles, contacts)
        self.data = mujoco.MjData(self.model)
        m = self.model
        self.hand_qadr = np.array([m.jnt_qposadr[m.joint(f"hand_{a}").id] for a in "xyz"])
        self.hand_dadr = np.array([m.jnt_dofadr[m.joint(f"hand_{a}").id] for a in "xyz"])
        self.obj_qadr = m.jnt_qposadr[m.joint("object_joint").id]
        self.obj_dadr = m.jnt_dofadr[m.joint("object_joint").id]
        self.obj_body = m.body("object").id
        self.clutter_qadr = [m.jnt_qposadr[m.joint(f"clutter{i}_joint").id] for i in range(len(clutter))]
        self.goal_mocap = m.body_mocapid[m.body("goal").id]
        hand_body = m.body("hand").id
        self.hand_geoms = np.flatnonzero(m.geom_bodyid == hand_body)
        self._is_hand_geom = m.geom_bodyid == hand_body  # by geom id
        force = m.sensor("hand_contact_force")
        self._hand_force = slice(force.adr[0], force.adr[0] + 3)  # in sensordata
        self.free_dofs = np.concatenate(  # the free bodies' dofs: settle waits for them to rest
            [np.arange(m.jnt_dofadr[j], m.jnt_dofadr[j] + 6) for j in np.flatnonzero(m.jnt_type == 0)]
        )
        self._rollout = rollout.Rollout(nthread=0)  # runs on the calling thread
        self._poses: dict[str, tuple[bytes, np.ndarray]] = {}  # object_T's, by body
        self._surface: tuple[bytes, np.ndarray] | None = None  # object_surface's
        self.reset()

    # --- state accessors -------------------------------------------------------------------------
    def reset(self) -> None:
        """Reset all simulation state (incl. solver warm-start, so episodes replay exactly)."""
        mujoco.mj_resetData(self.model, self.data)
        self.reset_hand()

    def reset_hand(self, forward: bool = True) -> None:
        """Park the hand (keyframe ``home``) without touching the rest of the state. ``forward=False``
        leaves ``mj_forward`` to the ``mj_step`` that follows (it changes no state, only derived
        quantities that step recomputes)."""
        d = self.data
        d.qpos[self.hand_qadr] = PARK_POS
        d.qvel[self.hand_dadr] = 0.0
        d.ctrl[:] = PARK_POS
        if forward:
            mujoco.mj_forward(self.model, d)

    def set_object_pose(self, pos: np.ndarray, quat_wxyz: np.ndarray, body: str = "object") -> None:
        adr = self.obj_qadr if body == "object" else self.clutter_qadr[int(body.removeprefix("clutter"))]
        dadr = self.model.jnt_dofadr[self.model.joint(f"{body}_joint").id]
        self.data.qpos[adr : adr + 3] = pos
        self.data.qpos[adr + 3 : adr + 7] = np.asarray(quat_wxyz) / np.linalg.norm(quat_wxyz)
        self.data.qvel[dadr : dadr + 6] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def object_pose(self, body: str = "object") -> tuple[np.ndarray, np.ndarray]:
        """``(pos (3,), quat (4,) wxyz)`` of a free body, copies."""
        adr = self.obj_qadr if body == "object" else self.clutter_qadr[int(body.removeprefix("clutter"))]
        q = self.data.qpos[adr : adr + 7]
        return q[:3].copy(), q[3:7].copy()

    def object_surface(self) -> np.ndarray:
        """The object's surface samples ``(P, 3)`` in the world frame at its pose (read-only): the
        observation, the symmetric goal and the reward all read them, made once per pose."""
        key = self.data.qpos[self.obj_qadr : self.obj_qadr + 7].tobytes()
        if self._surface is None or self._surface[0] != key:
            points = transform_points(self.object_T(), self.asset.surface_points)
            points.flags.writeable = False
            self._surface = (key, points)
        return self._surface[1]

    def object_T(self, body: str = "object") -> np.ndarray:
        """``(4, 4)`` pose of a free body (a copy), made once per pose: the env reads it several times
        in one state (goal, reward, observation)."""
        adr = self.obj_qadr if body == "object" else self.clutter_qadr[int(body.removeprefix("clutter"))]
        key = self.data.qpos[adr : adr + 7].tobytes()
        cached = self._poses.get(body)
        if cached is None or cached[0] != key:
            cached = self._poses[body] = (key, pose_matrix(*self.object_pose(body)))
        return cached[1].copy()

    def set_goal_ghost(self, pos: np.ndarray, quat_wxyz: np.ndarray) -> None:
        self.data.mocap_pos[self.goal_mocap] = pos
        self.data.mocap_quat[self.goal_mocap] = quat_wxyz

    def object_speed(self) -> tuple[float, float]:
        """``(linear m/s, angular rad/s)`` of the object."""
        v = self.data.qvel[self.obj_dadr : self.obj_dadr + 6]
        return float(np.linalg.norm(v[:3])), float(np.linalg.norm(v[3:]))

    def object_in_bin(self) -> bool:
        """False once the object's origin has left the bin's inner volume (with a 2 cm margin)."""
        pos, _ = self.object_pose()
        half = BIN_INNER_SIZE_M[:2] / 2 + 0.02
        return bool(np.all(np.abs(pos[:2]) < half) and -0.02 < pos[2] < 0.35)

    def get_state(self) -> np.ndarray:
        """MuJoCo's full integration state (1-D float64): positions, velocities, controls, mocap
        poses, time and the solver's warm start, so that ``set_state`` replays a push exactly."""
        state = np.empty(mujoco.mj_stateSize(self.model, _FULL_STATE))
        mujoco.mj_getState(self.model, self.data, state, _FULL_STATE)
        return state

    def set_state(self, state: np.ndarray) -> None:
        mujoco.mj_setState(self.model, self.data, np.asarray(state, dtype=np.float64), _FULL_STATE)
        mujoco.mj_forward(self.model, self.data)

    # --- physics ---------------------------------------------------------------------------------
    def settle(self, max_s: float = SETTLE_MAX_S, chunk: int = 5) -> int:
        """Step until every free body is at rest (or ``max_s``); returns physics steps taken.

        Faster than HACMan's fixed 2 s wait: most pushes leave the object at rest within 0.2 s.
        """
        m, d = self.model, self.data
        n_max = int(max_s / m.opt.timestep)
        steps = 0
        calm = 0
        free_dofs, qvel = self.free_dofs, d.qvel
        while steps < n_max:
            mujoco.mj_step(m, d, nstep=chunk)
            steps += chunk
            if _at_rest(qvel[free_dofs].tolist()):
                calm += 1
                if calm >= 2:
                    break
            else:
                calm = 0
        return steps

    def _hand_penetration(self) -> float:
        """Deepest penetration (m, >= 0) of any hand geom into anything (vectorised over contacts)."""
        d = self.data
        if d.ncon == 0:
            return 0.0
        hand = self._is_hand_geom[d.contact.geom[: d.ncon]].any(axis=1)
        return float(max(0.0, -d.contact.dist[: d.ncon][hand].min())) if hand.any() else 0.0

    def execute_primitive(self, waypoints: np.ndarray) -> PrimitiveResult:
        """Run checked fingertip ``waypoints`` (N_WAYPOINTS, 3) from ``sim.primitive``, then settle.

        Teleports the hand to the pre-contact waypoint (HACMan does the same in training), moves
        through the rest with force-limited position control, parks the hand and waits for rest. A
        start pose inside the object, clutter or a wall is refused and leaves the state unchanged.
        With ``force_stop_n`` set, the primitive ends at the first physics step whose net contact
        force on the hand passes it, as the cell's contact-force stop ends a push on the arm (which
        then retracts and re-observes): the hand is parked from there.
        """
        m, d = self.model, self.data
        saved = self.get_state()
        d.qpos[self.hand_qadr] = waypoints[0]
        d.qvel[self.hand_dadr] = 0.0
        d.ctrl[:] = waypoints[0]
        mujoco.mj_forward(m, d)
        if self._hand_penetration() > START_PENETRATION_M:
            self.set_state(saved)
            return PrimitiveResult(False, "start pose in collision")
        # approach, pushes, then lift 6 cm so the hand leaves the object gently; then park
        controls = push_controls(waypoints, m.opt.timestep)
        stopped_at = self._run_controls(controls, self.force_stop_n)
        steps = len(controls) if stopped_at is None else stopped_at + 1
        self.reset_hand(forward=False)  # settle steps at once
        steps += self.settle()
        return PrimitiveResult(True, "", steps, stopped_at is not None)

    def _run_controls(self, controls: np.ndarray, force_stop_n: float | None = None) -> int | None:
        """``mj_step`` once per row of ``controls (T, nu)``, each row set as ``ctrl`` first; the other
        user inputs (mocap poses, applied forces) stay as they are. One ``mujoco.rollout`` call: the
        same steps as that Python loop, bit for bit, without its per-step overhead.

        With ``force_stop_n``: the index of the first step whose hand contact force (N) passes it,
        and the state is put back to the one after that step (the rest of the rollout is dropped);
        None when no step does (the state is the last step's)."""
        m, d = self.model, self.data
        initial = np.empty((1, mujoco.mj_stateSize(m, _PHYSICS_STATE)))
        mujoco.mj_getState(m, d, initial[0], _PHYSICS_STATE)
        user = np.empty(mujoco.mj_stateSize(m, _USER_STATE))
        mujoco.mj_getState(m, d, user, _USER_STATE)
        inputs = np.tile(user, (1, len(controls), 1))
        inputs[0, :, : m.nu] = controls
        warmstart = d.qacc_warmstart.copy()[None]
        states = np.empty((1, len(controls), initial.shape[1]))
        sensordata = np.empty((1, len(controls), m.nsensordata))
        # skip_checks: the arrays are made here with the shapes rollout's own checks would infer
        self._rollout.rollout(
            [m],
            [d],
            initial,
            inputs,
            control_spec=_USER_STATE,
            skip_checks=True,
            nstep=len(controls),
            initial_warmstart=warmstart,
            state=states,
            sensordata=sensordata,
        )
        if force_stop_n is None:
            return None
        f = sensordata[0, :, self._hand_force]
        over = np.flatnonzero(np.einsum("ij,ij->i", f, f) > force_stop_n**2)
        if len(over) == 0:
            return None
        k = int(over[0])
        mujoco.mj_setState(m, d, states[0, k], _PHYSICS_STATE)
        return k
