"""The executor contract: one interface for the Panda, the FR3, the MuJoCo twin and the test fakes.

Shaped like LeRobot's ``Robot``: a context manager that connects on enter and, on exit, stops the
arm and disconnects without ever hiding the exception that ended the block (a Ctrl-C stays a
Ctrl-C). ``execute(plan)`` sends a checked :class:`robot.safety.Plan` one command at a time and
returns what was actually commanded with one typed :class:`Outcome`, whatever the library's way of
failing (libfranka raises, franky's reactions return normally, panda-python returns ``False``)::

    with make_executor("sim", cell, log=log, world=world) as robot:   # robot.connect
        result = robot.execute(plan)          # ExecutionResult
        if result.outcome is Outcome.reflex: ...

Every command is written to the session log (and fsynced) *before* it is sent: after a crash or a
SIGKILL the log's last line is the last command the robot may have received.

Subclasses implement ``connect``, ``disconnect``, ``stop``, ``recover``, ``robot_mode``,
``fingertip`` and ``_move`` (one straight fingertip move, or the joint move home). The executors
are built by ``robot.connect.make_executor``, which imports ``panda_py`` / ``franky`` only when that
robot is selected; libfranka's error vocabulary (recoverable errors, operator actions) lives in
``robot.libfranka``.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np


class Outcome(str, enum.Enum):
    """How a plan (or one command) ended."""

    ok = "ok"  # every command reached its target
    short_of_goal = "short_of_goal"  # a move ended (deadline or impedance stall) away from its target
    reaction_fired = "reaction_fired"  # hydo's contact-force stop stopped a move (no robot error)
    reflex = "reflex"  # the robot's own reflex stopped it (cartesian_reflex, joint_reflex, ...)
    comm_lost = "comm_lost"  # connection lost or robot absent: never reconnect and continue
    critical = "critical"  # power/joint limit, self-collision, user stop, ...: a person must act


class RobotMode(str, enum.Enum):
    """libfranka's robot modes, as every executor reports them."""

    idle = "idle"
    move = "move"
    reflex = "reflex"
    user_stopped = "user_stopped"
    guiding = "guiding"
    automatic_error_recovery = "automatic_error_recovery"
    other = "other"
    disconnected = "disconnected"


CONTACT_KINDS = ("contact", "push")


@dataclass(frozen=True)
class Command:
    """One motion command: a straight fingertip move (hand pointing down) or the joint move home."""

    index: int  # position in its plan
    kind: str  # "transit" | "approach" | "contact" | "push" | "retract" | "home"
    target: tuple[float, float, float]  # fingertip, robot base frame, metres
    speed: float  # m/s, fingertip speed limit of this move
    label: str  # e.g. "w4 push 2"

    @property
    def in_contact(self) -> bool:
        """Contact and push moves end blocked by design (the fingertip is commanded onto and into the
        object's surface): they are never "short of goal", the contact-force stop guards them."""
        return self.kind in CONTACT_KINDS

    def to_json(self) -> dict:
        return {
            "index": self.index,
            "kind": self.kind,
            "target": [round(float(v), 6) for v in self.target],
            "speed": self.speed,
            "label": self.label,
        }


@dataclass
class MoveResult:
    """What one command ended with (returned by ``Executor._move``)."""

    outcome: Outcome
    position: np.ndarray  # fingertip (3,) at the end, base frame, metres
    peak_force: float = 0.0  # N, largest |F_ext| seen during the move (0 when unknown)
    errors: tuple[str, ...] = ()  # libfranka error names, for reflex / critical
    message: str = ""


@dataclass
class ExecutionResult:
    """What ``execute`` did: the commands actually sent, in order, and how it ended."""

    outcome: Outcome
    commanded: list[Command] = field(default_factory=list)
    failed: Command | None = None  # the command that ended badly (None when ok)
    errors: tuple[str, ...] = ()
    robot_mode: str = "idle"
    peak_force: float = 0.0
    position: np.ndarray | None = None
    message: str = ""
    duration_s: float = 0.0

    def to_json(self) -> dict:
        return {
            "outcome": self.outcome.value,
            "commanded": [c.index for c in self.commanded],
            "failed": None if self.failed is None else self.failed.to_json(),
            "errors": list(self.errors),
            "robot_mode": self.robot_mode,
            "peak_force_n": round(float(self.peak_force), 3),
            "position": None if self.position is None else np.round(self.position, 5).tolist(),
            "message": self.message,
            "duration_s": round(self.duration_s, 3),
        }


class Executor(ABC):
    """Base of every executor; see the module docstring for the contract."""

    name = "executor"

    def __init__(self, cell, log=None, speed_scale: float = 1.0):
        if not 0.0 < speed_scale <= 1.0:
            raise ValueError(
                f"`speed_scale` must be in (0, 1] (it only slows the cell's speeds down). Got {speed_scale!r}."
            )
        self.cell = cell
        self.log = log  # robot.session_log.SessionLog or None
        self.speed_scale = float(speed_scale)  # every command's speed is multiplied by this
        self.commands_sent = 0  # every motion command passed to the robot library
        self.connected = False
        self.last_motion_end = 0.0  # time.time() when the last move ended (stale-frame check)

    # --- context manager ---------------------------------------------------------------------------
    def __enter__(self) -> Executor:
        self.connect()
        self.connected = True
        if self.log is not None:
            self.log.event("robot_connected", robot=self.name, limits=self.cell.summary())
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        try:
            if self.connected:
                self.stop()
        except Exception as stop_error:  # never hide the error that ended the block
            if exc is None:
                raise
            if self.log is not None:
                self.log.event("stop_failed", error=repr(stop_error))
        finally:
            try:
                self.disconnect()
            finally:
                self.connected = False
        return False

    # --- what each robot implements ----------------------------------------------------------------
    @abstractmethod
    def connect(self) -> None:
        """Open the connection, recover, set every limit from the cell (log them); raise on failure."""

    @abstractmethod
    def disconnect(self) -> None: ...

    @abstractmethod
    def stop(self) -> None:
        """Bring the arm to rest now (Ctrl-C, errors)."""

    @abstractmethod
    def recover(self) -> None:
        """Clear a reflex (libfranka's automatic error recovery)."""

    @abstractmethod
    def robot_mode(self) -> RobotMode: ...

    @abstractmethod
    def current_errors(self) -> tuple[str, ...]:
        """Active libfranka error names (may clear while the mode still says reflex)."""

    @abstractmethod
    def fingertip(self) -> np.ndarray:
        """Fingertip position (3,) in the base frame, metres."""

    @abstractmethod
    def joints(self) -> np.ndarray:
        """Joint positions (7,) rad."""

    @abstractmethod
    def _move(self, command: Command) -> MoveResult:
        """Execute one command, classified into a ``MoveResult``; never raise for robot errors."""

    # --- shared ------------------------------------------------------------------------------------
    def at_home(self, tol_rad: float = 0.1) -> bool:
        return bool(np.abs(self.joints() - self.cell.home_joints).max() <= tol_rad)

    def send(self, command: Command) -> MoveResult:
        """Log ``command`` (fsynced), then send it. The log line always precedes the motion."""
        if not self.connected:
            raise RuntimeError(f"{self.name}: not connected (use `with executor:` first)")
        if self.speed_scale != 1.0:
            command = dataclasses.replace(command, speed=command.speed * self.speed_scale)
        if self.log is not None:
            self.log.command(self.name, command)
        self.commands_sent += 1
        try:
            result = self._move(command)
        finally:
            self.last_motion_end = time.time()
        if self.log is not None:
            self.log.event(
                "command_done",
                index=command.index,
                label=command.label,
                outcome=result.outcome.value,
                position=np.round(result.position, 5).tolist(),
                peak_force_n=round(float(result.peak_force), 3),
                errors=list(result.errors),
            )
        return result

    def execute(self, plan) -> ExecutionResult:
        """Send ``plan.commands`` in order; stop at the first one that does not end ``ok``.

        A command after a failed one is never sent (a reflex on push 2 means push 3 never goes out).
        """
        t0 = time.time()
        sent: list[Command] = []
        peak = 0.0
        last: MoveResult | None = None
        for command in plan.commands:
            sent.append(command)
            last = self.send(command)
            peak = max(peak, last.peak_force)
            if last.outcome is not Outcome.ok:
                mode = self._safe_mode()
                return ExecutionResult(
                    last.outcome,
                    sent,
                    command,
                    last.errors,
                    mode.value,
                    peak,
                    last.position,
                    last.message,
                    time.time() - t0,
                )
        return ExecutionResult(
            Outcome.ok,
            sent,
            None,
            (),
            self._safe_mode().value,
            peak,
            None if last is None else last.position,
            "",
            time.time() - t0,
        )

    def _safe_mode(self) -> RobotMode:
        try:
            return self.robot_mode()
        except Exception:
            return RobotMode.disconnected
