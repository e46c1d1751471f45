"""Franka Research 3 through franky (``franky-control``, libfranka 0.21). Imported lazily.

franky's failure style (robot-safety.md): control errors raise ``ControlException``, a lost
connection raises ``NetworkException``, but a *reaction* that fires makes ``move`` return normally:
this executor registers a callback on its force reaction and reports ``reaction_fired`` itself.
franky's relative moves are in the end-effector frame (a −5 cm z move raised the hand), so every
move here is an absolute base-frame target composed from the fingertip target and ``F_T_EE``.

On connect, franky's ritual with every limit from the cell: ``recover_from_errors()``, a low global
``relative_dynamics_factor``, explicit collision thresholds (``set_collision_behavior``), and the
realtime kernel enforced unless ``--allow-no-realtime`` (then ``RealtimeConfig.Ignore``, logged).
Each Cartesian move carries a reaction ``|F_ext|² > F_stop²`` → ``CartesianStopMotion``; its speed is
the command's, through the motion's relative dynamics factor. Every move, the joint move home
included, also carries the cell's deadline ``REL_TIME > motion_timeout_s`` → stop, reported as
``short_of_goal``.
"""

from __future__ import annotations

import threading
import time

import numpy as np

from robot.arm import R_DOWN
from robot.errors import RobotConnectionError
from robot.executor import Command, Executor, MoveResult, Outcome, RobotMode
from robot.libfranka import classify_errors, error_names, fingertip_to_ee

GLOBAL_DYNAMICS_FACTOR = 0.1  # franky's examples use 0.05-0.1; every move scales below this
JOINT_MOVE_FACTOR = 0.5  # of the global factor, for the joint move home
PLANNER_RETRY_PAUSE_S = 0.3  # s, before replanning a free-space move franky's planner failed on
MODES = {
    "Other": RobotMode.other,
    "Idle": RobotMode.idle,
    "Move": RobotMode.move,
    "Guiding": RobotMode.guiding,
    "Reflex": RobotMode.reflex,
    "UserStopped": RobotMode.user_stopped,
    "AutomaticErrorRecovery": RobotMode.automatic_error_recovery,
}


def _import_franky():
    try:
        import franky
    except ImportError as e:
        raise RobotConnectionError(
            f"franky is not installed or cannot load ({e}): `pip install franky-control==2.0.0`"
        ) from None
    return franky


def _limit_value(v) -> float:
    """franky exposes dynamics limits as ``DoubleDynamicsLimit`` objects (``.get()``) or floats."""
    return float(v.get()) if hasattr(v, "get") else float(getattr(v, "value", v))


def _matrix(T) -> np.ndarray:
    """A (4, 4) array from franky's ``Affine`` (``.matrix``) or libfranka's column-major 16-vector."""
    m = getattr(T, "matrix", None)
    return np.asarray(m if m is not None else np.asarray(T).reshape(4, 4, order="F"), dtype=np.float64)


class FR3Executor(Executor):
    """The executor contract on an FR3 through franky (see the module docstring)."""

    name = "fr3"

    def __init__(self, cell, log=None, allow_no_realtime: bool = False, speed_scale: float = 1.0):
        super().__init__(cell, log, speed_scale)
        self.allow_no_realtime = allow_no_realtime
        self.robot = None
        self._fr = None
        self._tip_to_ee = None
        self._v_limit = 1.0

    def connect(self) -> None:
        fr = self._fr = _import_franky()
        lim = self.cell.limits
        rt = fr.RealtimeConfig.Ignore if self.allow_no_realtime else fr.RealtimeConfig.Enforce
        try:
            self.robot = fr.Robot(
                self.cell.address,
                relative_dynamics_factor=GLOBAL_DYNAMICS_FACTOR,
                default_torque_threshold=lim.collision_torque,
                default_force_threshold=lim.collision_force,
                realtime_config=rt,
            )
        except Exception as e:  # NetworkException, IncompatibleVersionException, RealtimeException
            first = str(e).splitlines()[0] if str(e) else type(e).__name__
            raise RobotConnectionError(
                f"cannot connect to the FR3 at {self.cell.address} ({type(e).__name__}: {first}): check the address in "
                "the cell file, the network cable and that FCI is activated in Desk"
            ) from None
        r = self.robot
        r.recover_from_errors()
        r.relative_dynamics_factor = GLOBAL_DYNAMICS_FACTOR
        r.set_collision_behavior([lim.collision_torque] * 7, [lim.collision_force] * 6)
        F_T_EE = _matrix(r.state.F_T_EE)
        self._tip_to_ee = fingertip_to_ee(self.cell, F_T_EE)
        self._v_limit = _limit_value(r.translation_velocity_limit)
        if self.log is not None:
            self.log.event(
                "limits_set",
                robot=self.name,
                relative_dynamics_factor=GLOBAL_DYNAMICS_FACTOR,
                collision_torque_nm=lim.collision_torque,
                collision_force_n=lim.collision_force,
                force_stop_n=lim.force_stop,
                translation_velocity_limit_mps=self._v_limit,
                realtime="ignored (--allow-no-realtime)" if self.allow_no_realtime else "enforced",
                F_T_EE=F_T_EE.round(6).tolist(),
            )

    def disconnect(self) -> None:
        self.robot = None

    def stop(self) -> None:
        if self.robot is not None:
            try:
                self.robot.stop()
            except Exception:
                pass  # not moving

    def recover(self) -> None:
        self.robot.recover_from_errors()

    def robot_mode(self) -> RobotMode:
        mode = self.robot.state.robot_mode
        return MODES.get(getattr(mode, "name", str(mode).split(".")[-1]), RobotMode.other)

    def current_errors(self) -> tuple[str, ...]:
        return error_names(self.robot.state.current_errors)

    def joints(self) -> np.ndarray:
        return np.asarray(self.robot.current_joint_positions, dtype=np.float64)

    def fingertip(self) -> np.ndarray:
        O_T_EE = _matrix(self.robot.current_pose.end_effector_pose)
        return (O_T_EE @ np.linalg.inv(self._tip_to_ee))[:3, 3]

    def _factor(self, speed: float) -> float:
        """The motion's relative dynamics factor for a fingertip speed (m/s) under the global factor."""
        return float(np.clip(speed / (self._v_limit * GLOBAL_DYNAMICS_FACTOR), 1e-3, 1.0))

    def _classify(self, e: Exception | None, what: str) -> MoveResult:
        fr = self._fr
        if e is not None and isinstance(e, fr.NetworkException):
            return MoveResult(Outcome.comm_lost, np.full(3, np.nan), 0.0, (), f"{what}: {e}")
        try:
            state = self.robot.state
        except Exception as e2:
            return MoveResult(Outcome.comm_lost, np.full(3, np.nan), 0.0, (), f"{what}: {e2}")
        errors = tuple(
            sorted(set(error_names(state.current_errors)) | set(error_names(state.last_motion_errors)))
        )
        mode = self.robot_mode()
        pos = self.fingertip()
        if mode is RobotMode.user_stopped:
            return MoveResult(
                Outcome.critical, pos, 0.0, errors + ("user_stop",), f"{what}: user stop pressed"
            )
        if not errors and mode is RobotMode.reflex:
            return MoveResult(Outcome.reflex, pos, 0.0, (), f"{what}: robot latched in reflex")
        return MoveResult(classify_errors(errors), pos, 0.0, errors, f"{what}: {e}")

    def _motion(self, command: Command):
        """franky's motion for ``command`` with its reactions, and the events they set."""
        fr = self._fr
        lim = self.cell.limits
        fired, timed_out = threading.Event(), threading.Event()
        M = fr.Measure
        if command.kind == "home":
            motion = fr.JointMotion(
                fr.JointState(np.asarray(self.cell.home_joints, dtype=np.float64)),
                relative_dynamics_factor=JOINT_MOVE_FACTOR,
            )
            stop = fr.JointStopMotion()
        else:
            T = np.eye(4)
            T[:3, :3], T[:3, 3] = R_DOWN, command.target
            motion = fr.CartesianMotion(
                fr.Affine(T @ self._tip_to_ee),
                fr.ReferenceType.Absolute,
                relative_dynamics_factor=self._factor(command.speed),
            )
            stop = fr.CartesianStopMotion()
            force2 = M.FORCE_X * M.FORCE_X + M.FORCE_Y * M.FORCE_Y + M.FORCE_Z * M.FORCE_Z
            reaction = fr.Reaction(force2 > lim.force_stop**2, stop)
            reaction.register_callback(lambda *_: fired.set())
            motion.add_reaction(reaction)
        # The cell's deadline on every move (REL_TIME is seconds since this motion started): a move
        # that cannot finish (a stall against the bin, a target the controller creeps towards) stops
        # where it is instead of blocking the session.
        deadline = fr.Reaction(M.REL_TIME > lim.motion_timeout, stop)
        deadline.register_callback(lambda *_: timed_out.set())
        motion.add_reaction(deadline)
        return motion, fired, timed_out

    def _move(self, command: Command) -> MoveResult:
        fr = self._fr
        lim = self.cell.limits
        # franky's trajectory generator (ruckig) can fail to plan from the state the arm is in (seen
        # on franky-sim as `RuntimeError: Motion planner failed with error code -111`, a
        # synchronisation failure when a move starts while the arm still drifts after the last one).
        # It is not a robot error: no flag is set and the arm holds. A free-space move is replanned
        # once, to the same gate-checked target, after a pause; a contact move is not, since a
        # second push is a different interaction. A second failure ends the move short of its goal,
        # so the loop retracts (checked) and goes on, never a traceback.
        for attempt in (1, 2):
            motion, fired, timed_out = self._motion(command)
            try:
                self.robot.move(motion)
                break
            except Exception as e:  # ControlException (reflex, limits), NetworkException, CommandException
                if isinstance(e, fr.Exception):
                    return self._classify(e, command.label)
                if not isinstance(e, RuntimeError) or "planner" not in str(e).lower():
                    raise
                if attempt == 2 or command.in_contact or self.robot_mode() is not RobotMode.idle:
                    return MoveResult(
                        Outcome.short_of_goal,
                        self.fingertip(),
                        0.0,
                        (),
                        f"{command.label}: franky's motion planner failed ({e})",
                    )
                if self.log is not None:
                    self.log.event("planner_retry", label=command.label, error=str(e))
                time.sleep(PLANNER_RETRY_PAUSE_S)
        here = self.fingertip()
        if timed_out.is_set():
            return MoveResult(
                Outcome.short_of_goal,
                here,
                0.0,
                (),
                f"{command.label}: deadline of {lim.motion_timeout:g} s reached",
            )
        if fired.is_set():
            return MoveResult(
                Outcome.reaction_fired, here, lim.force_stop, (), f"force reaction > {lim.force_stop:g} N"
            )
        if command.kind != "home" and not command.in_contact:
            err = float(np.linalg.norm(here - np.asarray(command.target)))
            if err > lim.position_tolerance:
                return MoveResult(Outcome.short_of_goal, here, 0.0, (), f"stopped {err * 1000:.0f} mm short")
        return MoveResult(Outcome.ok, here)
