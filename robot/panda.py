"""Franka Panda (FER) through panda-python (``panda_py``, bundling libfranka 0.9.2). Imported lazily.

panda-python's failure style (robot-safety.md): its motions *return* ``False`` on a control error
instead of raising, its controllers run in their own thread, and it clears reflexes by itself
before a move. So after every move this executor calls ``raise_error()`` and classifies from the
robot state's error flags and mode, never from exception text.

Cartesian moves run panda-python's ``CartesianImpedance`` torque controller with the cell's
stiffness; a Python loop at ``CONTROL_HZ`` moves the reference along the straight line at the
command's speed and stops the move when |F_ext| (``O_F_ext_hat_K``) exceeds the cell's force stop
(``reaction_fired``). The robot's collision reflex thresholds are set from the cell on connect. The
joint move home is ``move_to_joint_position``. Fingertip targets are turned into the robot's
end-effector frame with ``F_T_EE`` read from the robot, so Desk's TCP setting never shifts a push.
"""

from __future__ import annotations

import numpy as np

from robot.arm import R_DOWN, quat_from_matrix
from robot.errors import RobotConnectionError
from robot.executor import Command, Executor, MoveResult, Outcome, RobotMode
from robot.libfranka import classify_errors, error_names, fingertip_to_ee

CONTROL_HZ = 100.0  # reference updates and force checks per second (the torque loop runs at 1 kHz)
SETTLE_MAX_S = 1.0  # after the reference arrives, wait this long for the fingertip to follow
CONTACT_SETTLE_S = 0.2  # ... on contact and push moves (they end against the object)
ARRIVE_TOL_M = 0.003
PANDA_MAX_JOINT_SPEED_FACTOR = 0.2  # move_to_joint_position's speed factor for the move home
NULLSPACE_STIFFNESS = 0.5
#: libfranka RobotMode names -> ours
MODES = {
    "kOther": RobotMode.other,
    "kIdle": RobotMode.idle,
    "kMove": RobotMode.move,
    "kGuiding": RobotMode.guiding,
    "kReflex": RobotMode.reflex,
    "kUserStopped": RobotMode.user_stopped,
    "kAutomaticErrorRecovery": RobotMode.automatic_error_recovery,
}


def _import_panda_py():
    try:
        import panda_py
        import panda_py.controllers
    except ImportError as e:
        raise RobotConnectionError(
            f"panda-python is not installed or cannot load ({e}): `pip install panda-python==1.1.1`"
        ) from None
    return panda_py


def mode_of(state) -> RobotMode:
    name = getattr(state.robot_mode, "name", str(state.robot_mode).split(".")[-1])
    return MODES.get(name, RobotMode.other)


class PandaExecutor(Executor):
    """The executor contract on a Panda through panda-python (see the module docstring)."""

    name = "panda"

    def __init__(self, cell, log=None, allow_no_realtime: bool = False, speed_scale: float = 1.0):
        super().__init__(cell, log, speed_scale)
        self.allow_no_realtime = allow_no_realtime
        self.panda = None
        self._pp = None
        self._tip_to_ee = None

    # --- connection ----------------------------------------------------------------------------------
    def connect(self) -> None:
        # The realtime kernel is checked at start-up by the deploy loop (panda-python ignores it).
        pp = self._pp = _import_panda_py()
        address = self.cell.address
        try:
            self.panda = pp.Panda(address)
        except Exception as e:  # libfranka's NetworkException and friends surface as RuntimeError
            raise RobotConnectionError(
                f"cannot connect to the Panda at {address} ({str(e).splitlines()[0] if str(e) else type(e).__name__}): "
                "check the address in the cell file, the network cable and that FCI is activated in Desk"
            ) from None
        self.panda.recover()
        lim = self.cell.limits
        robot = self.panda.get_robot()
        # lower thresholds: contact flags; upper thresholds: the collision reflex
        robot.set_collision_behavior(
            [lim.collision_torque * 0.5] * 7,
            [lim.collision_torque] * 7,
            [lim.force_stop] * 6,
            [lim.collision_force] * 6,
        )
        F_T_EE = np.asarray(self.panda.get_state().F_T_EE, dtype=np.float64).reshape(4, 4, order="F")
        self._tip_to_ee = fingertip_to_ee(self.cell, F_T_EE)
        if self.log is not None:
            self.log.event(
                "limits_set",
                robot=self.name,
                collision_torque_nm=[lim.collision_torque * 0.5, lim.collision_torque],
                collision_force_n=[lim.force_stop, lim.collision_force],
                cartesian_stiffness_npm=lim.cartesian_stiffness,
                F_T_EE=F_T_EE.round(6).tolist(),
            )

    def disconnect(self) -> None:
        self.panda = None

    def stop(self) -> None:
        if self.panda is not None:
            try:
                self.panda.stop_controller()
            except Exception:
                pass  # nothing running

    def recover(self) -> None:
        self.panda.recover()

    # --- state ---------------------------------------------------------------------------------------
    def _state(self):
        return self.panda.get_state()

    def robot_mode(self) -> RobotMode:
        return mode_of(self._state())

    def current_errors(self) -> tuple[str, ...]:
        return error_names(self._state().current_errors)

    def joints(self) -> np.ndarray:
        return np.asarray(self._state().q, dtype=np.float64)

    def fingertip(self) -> np.ndarray:
        O_T_EE = np.asarray(self._state().O_T_EE, dtype=np.float64).reshape(4, 4, order="F")
        return (O_T_EE @ np.linalg.inv(self._tip_to_ee))[:3, 3]

    # --- motion --------------------------------------------------------------------------------------
    def _classify_failure(self, what: str) -> MoveResult:
        """After a move that returned False or stopped early: raise_error(), then read the state."""
        raised = ""
        try:
            self.panda.raise_error()
        except RuntimeError as e:  # the error itself; classified from the flags below, not its text
            raised = str(e).splitlines()[0] if str(e) else "RuntimeError"
        try:
            state = self._state()
        except Exception as e:
            return MoveResult(Outcome.comm_lost, np.full(3, np.nan), 0.0, (), f"{what}: {e}")
        mode = mode_of(state)
        errors = tuple(
            sorted(set(error_names(state.current_errors)) | set(error_names(state.last_motion_errors)))
        )
        pos = self.fingertip()
        if (
            "communication_constraints_violation" not in errors
            and not errors
            and mode is RobotMode.idle
            and not raised
        ):
            return MoveResult(
                Outcome.short_of_goal, pos, 0.0, (), f"{what}: ended without reaching its target"
            )
        if mode is RobotMode.user_stopped:
            return MoveResult(
                Outcome.critical, pos, 0.0, errors + ("user_stop",), f"{what}: user stop pressed"
            )
        if not errors and mode is RobotMode.reflex:  # latched: flags cleared, mode still in reflex
            return MoveResult(Outcome.reflex, pos, 0.0, (), f"{what}: robot latched in reflex ({raised})")
        return MoveResult(classify_errors(errors), pos, 0.0, errors, f"{what}: {raised or ', '.join(errors)}")

    def _move(self, command: Command) -> MoveResult:
        try:
            if command.kind == "home":
                ok = self.panda.move_to_joint_position(
                    [np.asarray(self.cell.home_joints, dtype=np.float64)],
                    speed_factor=PANDA_MAX_JOINT_SPEED_FACTOR,
                )
                return (
                    MoveResult(Outcome.ok, self.fingertip()) if ok else self._classify_failure(command.label)
                )
            return self._cartesian(command)
        except RuntimeError as e:  # a libfranka exception that escaped (network loss, ...)
            try:
                self._state()
            except Exception:
                return MoveResult(Outcome.comm_lost, np.full(3, np.nan), 0.0, (), f"{command.label}: {e}")
            return self._classify_failure(command.label)

    def _ee_pose(self, tip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R_DOWN, tip
        E = T @ self._tip_to_ee
        q = quat_from_matrix(E[:3, :3])  # wxyz
        return E[:3, 3], np.array([q[1], q[2], q[3], q[0]])  # panda-python wants xyzw

    def _cartesian(self, command: Command) -> MoveResult:
        pp, lim = self._pp, self.cell.limits
        target = np.asarray(command.target, dtype=np.float64)
        start = self.fingertip()
        K = np.diag([lim.cartesian_stiffness] * 3 + [lim.rotational_stiffness] * 3)
        ctrl = pp.controllers.CartesianImpedance(
            impedance=K, damping_ratio=1.0, nullspace_stiffness=NULLSPACE_STIFFNESS
        )
        duration = float(np.linalg.norm(target - start)) / command.speed
        q_null = np.asarray(self.cell.home_joints, dtype=np.float64)
        peak = 0.0
        self.panda.start_controller(ctrl)
        try:
            with self.panda.create_context(frequency=CONTROL_HZ, max_runtime=lim.motion_timeout) as ctx:
                while ctx.ok():
                    t = ctx.num_ticks / CONTROL_HZ  # the context paces the loop at CONTROL_HZ
                    a = 1.0 if duration <= 0 else min(1.0, t / duration)
                    pos, quat = self._ee_pose(start + (target - start) * a)
                    ctrl.set_control(pos, quat, q_null)
                    state = self._state()
                    f = float(np.linalg.norm(np.asarray(state.O_F_ext_hat_K, dtype=np.float64)[:3]))
                    peak = max(peak, f)
                    if f > lim.force_stop:  # hydo's contact-force stop: hold where we are
                        here = self.fingertip()
                        pos, quat = self._ee_pose(here)
                        ctrl.set_control(pos, quat, q_null)
                        return MoveResult(
                            Outcome.reaction_fired,
                            here,
                            peak,
                            (),
                            f"|F_ext| {f:.1f} N > {lim.force_stop:g} N",
                        )
                    if a >= 1.0 and (
                        np.linalg.norm(self.fingertip() - target) < ARRIVE_TOL_M
                        or t > duration + SETTLE_MAX_S
                    ):
                        break
        finally:
            self.panda.stop_controller()
        failure = self._classify_failure(command.label) if not self._healthy() else None
        if failure is not None:
            failure.peak_force = peak
            return failure
        here = self.fingertip()
        err = float(np.linalg.norm(here - target))
        if err > lim.position_tolerance and not command.in_contact:
            return MoveResult(Outcome.short_of_goal, here, peak, (), f"stopped {err * 1000:.0f} mm short")
        return MoveResult(Outcome.ok, here, peak)

    def _healthy(self) -> bool:
        state = self._state()
        return mode_of(state) in (RobotMode.idle, RobotMode.move) and not error_names(state.current_errors)
