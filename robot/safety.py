"""Deploy's safety layers, innermost first. Nothing here moves anything; every refusal raises.

1. **hydo's own checks, before any command** (:class:`SafetyGate`): finite observation tensors of
   the right shapes, a non-empty object segmentation, finite policy outputs, and a plan from
   ``sim.primitive.primitive_waypoints`` (fingertip clamped 5 mm above the bin floor) that
   ``sim.primitive.check_plan`` accepts inside the cell's workspace box, transits above the bin
   rim, and the arm's kinematics can follow with every joint ≥ 0.1 rad inside its limits
   (``robot.arm``). The speed of every command comes from the cell (≤ 0.10 m/s transit, ≤ 0.05 m/s
   pushing). A refused plan is never clipped or repaired.
2. **The robot's reflexes** (collision thresholds set from the cell on connect, by the executor):
   a last-resort stop we expect and handle (:class:`RecoveryBudget`), never a safety function.
3. **A contact-force stop inside the motion** (franky reaction, panda-python force check, twin):
   a push is stopped when |F_ext| exceeds ``limits.force_stop_n`` (outcome ``reaction_fired``).

Physical safety is the stop device within reach and a person watching; these layers only make sure
hydo never *asks* for a bad motion.
"""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from robot.errors import (
    InputError,
    PerceptionError,
    RealtimeKernelError,
    RecoveryLimitError,
    RobotFaultError,
)
from robot.executor import Command, RobotMode
from robot.libfranka import RECOVERABLE_ERRORS
from sim.contract import FEATURE_DIM
from sim.primitive import (
    N_WAYPOINTS,
    PUSH_SEGMENTS,
    PrimitiveRejected,
    Workspace,
    check_plan,
    primitive_waypoints,
)

MAX_RECOVERIES_PER_EPISODE = 3  # the fourth reflex in an episode stops the run
MAX_RECOVERIES_PER_PRIMITIVE = 1
HOME_PATH_SAMPLES = 11  # the joint-space move home is checked at this many points
HOME_PATH_DIP_M = 0.02  # ... and may dip at most this far below the transit height
#: How far outside the workspace box a reflex or force stop may have left the fingertip for the
#: straight-up retract to start there (metres). The box is a bound on *planned* targets, inset from the
#: bin walls (``robot.cell`` checks it lies inside them); an arm stopped by a reflex can end a
#: millimetre or two past it (the twin: 1.2 mm at x after a 73 N reflex). Rising straight up from there
#: keeps x and y, so it moves no further out; refusing it would leave the arm in the bin. Farther out
#: than this is not a compliance overshoot: a person guides the arm.
RETRACT_START_TOLERANCE_M = 0.01
#: Labels of the primitive's waypoints (sim.primitive's geometry).
WAYPOINT_KINDS = ("approach", "approach", "contact", "push", "push", "push", "retract")
WAYPOINT_LABELS = (
    "w0 pre-contact",
    "w1 approach",
    "w2 contact",
    "w3 push 1",
    "w4 push 2",
    "w5 push 3",
    "w6 lift",
)


@dataclass(frozen=True)
class Plan:
    """A checked plan: the primitive's waypoints and the commands that execute it.

    ``commands``: transit from home to above w0 at the transit height, descend to w0, w1, w2, the
    three pushes, lift to w6, rise to the transit height, home. ``q`` holds the IK solution (7,) at
    each command's target (the twin follows it in its null space; real arms only need it to exist).
    """

    waypoints: np.ndarray  # (N_WAYPOINTS, 3) fingertip, base frame, metres
    commands: tuple[Command, ...]
    q: np.ndarray  # (len(commands), 7) rad
    min_joint_margin: float  # rad

    def table_rows(self) -> list[tuple[str, ...]]:
        """Rows ``(#, kind, label, x, y, z, speed)`` for the dry-run table."""
        return [
            (
                str(c.index),
                c.kind,
                c.label,
                f"{c.target[0]:+.3f}",
                f"{c.target[1]:+.3f}",
                f"{c.target[2]:+.3f}",
                f"{c.speed:.3f}",
            )
            for c in self.commands
        ]


class SafetyGate:
    """Checks every input and plan against the cell before anything is sent.

    ``kinematics``: a :class:`robot.arm.ArmKinematics` for the cell's arm (the twin passes its own).
    """

    def __init__(self, cell, kinematics=None):
        from robot.arm import ArmKinematics

        self.cell = cell
        self.kin = kinematics if kinematics is not None else ArmKinematics.for_cell(cell)
        self.home_position, _ = self.kin.fk(cell.home_joints)

    # --- inputs ------------------------------------------------------------------------------------
    @staticmethod
    def check_observation(obs: dict[str, np.ndarray], n_obj: int, n_bg: int) -> None:
        """Finite tensors with the contract's shapes and a non-empty object part; names the tensor."""
        n = n_obj + n_bg
        want = {"points": (n, 3), "features": (n, FEATURE_DIM), "normals": (n_obj, 3)}
        for name, shape in want.items():
            a = obs.get(name)
            if a is None:
                raise InputError(f"observation tensor `{name}` is missing")
            a = np.asarray(a)
            if a.shape != shape:
                raise InputError(f"observation tensor `{name}` has shape {a.shape}, expected {shape}")
            if not np.all(np.isfinite(a)):
                bad = int(np.count_nonzero(~np.isfinite(a)))
                raise InputError(
                    f"observation tensor `{name}` contains {bad} NaN/inf values: refusing to act"
                )
        if not np.all(obs["features"][:n_obj, 0] == 1.0):
            raise PerceptionError(
                "the observation has no object points (empty segmentation): refusing to act"
            )
        norms = np.linalg.norm(obs["normals"], axis=1)
        if np.any(norms < 0.5):
            raise InputError(
                "observation tensor `normals` has degenerate (zero-length) normals: refusing to act"
            )

    @staticmethod
    def check_action(index: int, motion: np.ndarray, n_obj: int) -> None:
        motion = np.asarray(motion, dtype=np.float64)
        if motion.shape != (3,) or not np.all(np.isfinite(motion)):
            raise InputError(f"policy output `motion` is not a finite 3-vector: {motion!r}")
        if not 0 <= int(index) < n_obj:
            raise InputError(f"policy output `index` {index} is outside the {n_obj} object points")

    # --- plans -------------------------------------------------------------------------------------
    def _transit_ok(self, a: np.ndarray, b: np.ndarray, what: str) -> None:
        z = self.cell.approach_z
        for p, name in ((a, "start"), (b, "end")):
            if p[2] < z - 1e-6:
                raise PrimitiveRejected(
                    f"{what}: transit {name} z={p[2]:.3f} m is below the transit height {z:.3f} m"
                )

    def plan_primitive(self, point: np.ndarray, normal: np.ndarray, motion: np.ndarray) -> Plan:
        """The checked plan of the push primitive at ``point`` (3,) / ``normal`` (3,) with ``motion``.

        Raises ``PrimitiveRejected`` (workspace: names waypoint, axis and bound), ``InputError``
        (non-finite inputs) or ``UnreachableError`` (kinematics) before anything moves.
        """
        for name, v in (("contact point", point), ("normal", normal), ("motion", motion)):
            v = np.asarray(v, dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise InputError(f"{name} is not a finite 3-vector: {v!r}")
        if np.linalg.norm(normal) < 0.5:
            raise InputError(f"normal {np.round(normal, 3).tolist()} is degenerate")
        w = primitive_waypoints(point, normal, motion, floor_z=self.cell.floor_z)
        check_plan(w, self.cell.workspace)
        lim = self.cell.limits
        z = self.cell.approach_z
        above_start = np.array([w[0, 0], w[0, 1], max(z, w[0, 2])])
        above_end = np.array([w[-1, 0], w[-1, 1], max(z, w[-1, 2])])
        check_plan(np.stack([above_start, above_end]), self.cell.workspace)
        self._transit_ok(self.home_position, above_start, "approach from home")
        targets, kinds, labels, speeds = [above_start], ["transit"], ["over w0"], [lim.transit_speed]
        for i in range(N_WAYPOINTS):
            targets.append(w[i])
            kinds.append(WAYPOINT_KINDS[i])
            labels.append(WAYPOINT_LABELS[i])
            # From pre-contact through the pushes: push speed; the lift and transits: transit speed.
            pushing = 1 <= i <= max(PUSH_SEGMENTS)
            speeds.append(lim.push_speed if pushing or i == 0 else lim.transit_speed)
        targets += [above_end, self.home_position]
        kinds += ["retract", "home"]
        labels += ["rise to transit height", "home"]
        speeds += [lim.transit_speed, lim.transit_speed]
        return self._finish(w, targets, kinds, labels, speeds, self.cell.home_joints)

    def plan_retract(self, position: np.ndarray, q_now: np.ndarray) -> Plan:
        """Checked retract from ``position`` (3,): straight up to the transit height, then home.

        Used after a reflex, a force stop or a short move: the old waypoints are never resumed. The
        start is where the stop left the arm, which may lie up to ``RETRACT_START_TOLERANCE_M``
        outside the workspace box; farther out raises ``RobotFaultError``.
        """
        position = np.asarray(position, dtype=np.float64)
        if position.shape != (3,) or not np.all(np.isfinite(position)):
            raise RobotFaultError("the arm reports a non-finite fingertip position: guide it home in Desk")
        lim = self.cell.limits
        up = np.array([position[0], position[1], max(position[2], self.cell.approach_z)])
        targets, kinds, labels, speeds = [], [], [], []
        if position[2] < self.cell.approach_z - 1e-3:
            self._retract_start_ok(position, up)
            targets.append(up)
            kinds.append("retract")
            labels.append("retract up")
            speeds.append(lim.transit_speed)
        self._transit_ok(up, self.home_position, "retract to home")
        targets.append(self.home_position)
        kinds.append("home")
        labels.append("home")
        speeds.append(lim.transit_speed)
        return self._finish(None, targets, kinds, labels, speeds, q_now)

    def _retract_start_ok(self, position: np.ndarray, up: np.ndarray) -> None:
        """Raise ``RobotFaultError`` unless the straight-up retract from ``position`` (3,), where a stop
        left the fingertip, to ``up`` (3,) passes the workspace gate with the box grown by
        ``RETRACT_START_TOLERANCE_M`` (the same ``check_plan``; only the box differs)."""
        ws, tol = self.cell.workspace, RETRACT_START_TOLERANCE_M
        grown = Workspace(tuple(np.asarray(ws.low) - tol), tuple(np.asarray(ws.high) + tol), ws.floor_z)
        try:
            check_plan(np.stack([position, up]), grown)
        except PrimitiveRejected as e:
            raise RobotFaultError(
                f"the fingertip stopped more than {tol * 1000:.0f} mm outside the workspace ({e}): "
                "not retracting automatically; guide the arm home in Desk"
            ) from None

    def _finish(self, w, targets, kinds, labels, speeds, q_start) -> Plan:
        targets = np.asarray(targets, dtype=np.float64)
        sol = self.kin.solve_path(targets, q_start, labels)
        if kinds[-1] == "home":  # real arms go home by a joint move: its path must stay above the bin
            q_from = sol.q[-2] if len(sol.q) > 1 else np.asarray(q_start, dtype=np.float64)
            for a in np.linspace(0.0, 1.0, HOME_PATH_SAMPLES):
                p, _ = self.kin.fk(q_from + (self.cell.home_joints - q_from) * a)
                if p[2] < self.cell.approach_z - HOME_PATH_DIP_M:
                    raise PrimitiveRejected(
                        f"the joint move home dips to z={p[2]:.3f} m, below the transit height "
                        f"{self.cell.approach_z:.3f} m: check robot.home_joints in the cell"
                    )
        commands = tuple(
            Command(i, k, tuple(float(v) for v in t), float(s), lab)
            for i, (t, k, lab, s) in enumerate(zip(targets, kinds, labels, speeds, strict=True))
        )
        wp = np.zeros((0, 3)) if w is None else w
        return Plan(wp, commands, sol.q, sol.min_margin_rad)


class RecoveryBudget:
    """Automatic recovery rules (robot-safety.md): only reflex/communication/discontinuity errors,
    at most once per primitive and ``MAX_RECOVERIES_PER_EPISODE`` times per episode; decided from
    the robot *mode* (error flags can clear while the mode is still latched in reflex)."""

    def __init__(self):
        self.episode = 0
        self.primitive = 0

    def new_episode(self) -> None:
        self.episode = 0
        self.primitive = 0

    def new_primitive(self) -> None:
        self.primitive = 0

    def authorise(self, mode: RobotMode, errors: tuple[str, ...], during: str = "") -> None:
        """Raise ``RobotFaultError`` unless an automatic recovery is allowed now; count it.

        A reflex beyond either limit is not recovered automatically, and a robot left in reflex mode
        cannot move: the run stops and a person inspects the cell. (A second reflex in one primitive
        is one during the checked retract after the first: the recovery itself failed.)"""
        what = ", ".join(errors) or mode.value
        where = f" during '{during}'" if during else ""
        unrecoverable = [e for e in errors if e not in RECOVERABLE_ERRORS]
        if unrecoverable:
            raise RobotFaultError(f"robot error {unrecoverable} is not recovered automatically")
        if mode not in (RobotMode.reflex, RobotMode.idle, RobotMode.other):
            raise RobotFaultError(f"robot is in mode '{mode.value}': not recovered automatically")
        if self.primitive >= MAX_RECOVERIES_PER_PRIMITIVE:
            raise RecoveryLimitError(
                f"a second reflex in one primitive ({what}{where}): at most {MAX_RECOVERIES_PER_PRIMITIVE} "
                "automatic recovery per primitive, stopping; guide the arm clear in Desk and inspect the cell"
            )
        if self.episode >= MAX_RECOVERIES_PER_EPISODE:
            raise RecoveryLimitError(
                f"reflex number {self.episode + 1} in this episode ({what}{where}): more than "
                f"{MAX_RECOVERIES_PER_EPISODE} recoveries per episode, stopping; inspect the cell"
            )
        self.primitive += 1
        self.episode += 1


def has_realtime_kernel() -> bool:
    """True on a PREEMPT_RT kernel (``/sys/kernel/realtime`` is 1, or the version says PREEMPT_RT)."""
    rt = Path("/sys/kernel/realtime")
    try:
        if rt.exists() and rt.read_text().strip() == "1":
            return True
    except OSError:
        pass
    return "PREEMPT_RT" in platform.uname().version or "PREEMPT RT" in platform.uname().version


def check_realtime(allow_override: bool, log=None) -> bool:
    """Refuse a real arm without a realtime kernel unless the override is given (and logged)."""
    if os.environ.get("HYDO_ASSUME_REALTIME") == "1" or has_realtime_kernel():
        return True
    if not allow_override:
        raise RealtimeKernelError(
            "no realtime (PREEMPT_RT) kernel: libfranka will stop with communication_constraints_violation; "
            "boot a realtime kernel, or pass --allow-no-realtime to accept the risk (it is logged)"
        )
    if log is not None:
        log.event("realtime_override", kernel=platform.uname().release, note="--allow-no-realtime given")
    return False
