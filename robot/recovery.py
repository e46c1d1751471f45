"""Fault recovery on the arm: what the deploy loop does after a plan that did not end ``ok``.

robot-safety.md's rules, in one function (:func:`handle_failure`): a lost connection
(``comm_lost``) or a critical error stops the run with what the person must do; a reflex is
recovered (decided by the robot mode, since flags may clear while the mode still latches) at most
once per primitive and three times per episode (``robot.safety.RecoveryBudget``); a contact-force
stop (``reaction_fired``) or a move short of its goal is an outcome of the step. Then, never resuming
the old waypoints, the arm retracts along a checked path (a reflex during the retract counts against
the same budget); the loop re-observes and re-plans.
"""

from __future__ import annotations

from robot.errors import RobotConnectionError, RobotFaultError
from robot.executor import ExecutionResult, Executor, Outcome, RobotMode
from robot.libfranka import operator_action


def handle_failure(result: ExecutionResult, robot: Executor, gate, budget, log, session, say) -> None:
    """Stop, recover or retract after a plan that did not end ``ok`` (robot-safety.md's rules).

    ``gate``: the ``robot.safety.SafetyGate`` that plans the retract; ``budget``: the
    ``robot.safety.RecoveryBudget`` (raises ``RobotFaultError`` / ``RecoveryLimitError`` when a
    recovery is not allowed); ``log``: the ``robot.session_log.SessionLog``; ``session``: the
    ``robot.report.SessionResult`` whose ``reflexes`` and ``force_stops`` are counted; ``say``: prints
    one line for the person.
    """
    where = result.failed.label if result.failed is not None else "?"
    if result.outcome is Outcome.comm_lost:
        raise RobotConnectionError(
            f"connection to the {robot.name} robot lost during '{where}' ({result.message}); not reconnecting: "
            f"check the network and the arm, then re-run (the log's last command is '{where}')"
        )
    if result.outcome is Outcome.critical:
        raise RobotFaultError(
            f"the {robot.name} robot stopped with {list(result.errors) or result.robot_mode} during '{where}': "
            f"{operator_action(result.errors)}. Not recovered automatically."
        )
    if result.outcome is Outcome.reflex:
        session.reflexes += 1
        mode = robot.robot_mode()
        errors = tuple(result.errors) or robot.current_errors()
        budget.authorise(mode, errors, where)  # raises RobotFaultError when not allowed
        log.event(
            "recovery",
            mode=mode.value,
            errors=list(errors),
            during=where,
            recoveries_this_episode=budget.episode,
        )
        say(f"reflex ({', '.join(errors) or mode.value}) during '{where}': recovering")
        if mode is RobotMode.reflex or errors:  # decided from the mode: flags may clear while it latches
            robot.recover()
        if robot.robot_mode() is RobotMode.reflex:
            robot.recover()
            if robot.robot_mode() is RobotMode.reflex:
                raise RobotFaultError(
                    "the robot stays in reflex mode after recovery: clear it in Desk, then re-run"
                )
    elif result.outcome is Outcome.reaction_fired:
        session.force_stops += 1
        log.event("force_stop", during=where, peak_force_n=result.peak_force)
        say(f"contact-force stop during '{where}' ({result.message}): retracting")
    # Never resume the old waypoints: retract along a checked path, then re-observe and re-plan.
    retract = gate.plan_retract(robot.fingertip(), robot.joints())
    log.event("retract", commands=[c.to_json() for c in retract.commands])
    r = robot.execute(retract)
    log.event("retract_outcome", **r.to_json())
    if r.outcome is Outcome.reflex:  # counts against the same budget; retracts again
        handle_failure(r, robot, gate, budget, log, session, say)
    elif r.outcome is not Outcome.ok:
        raise RobotFaultError(
            f"the retract after '{where}' ended '{r.outcome.value}' ({r.message}): guide the arm home"
        )
