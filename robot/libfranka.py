"""libfranka's vocabulary, one home for the Panda (panda-python) and FR3 (franky) executors.

Both libraries wrap libfranka, so both report the same error flags and the same flange frame:
:data:`RECOVERABLE_ERRORS` (what hydo recovers from by itself) and :data:`OPERATOR_ACTIONS` (what a
person must do about the rest), :func:`classify_errors` (flags -> ``reflex`` / ``critical``),
:func:`operator_action`, :func:`error_names` (the active flags of a libfranka ``Errors`` object) and
:func:`fingertip_to_ee` (the cell's fingertip in the robot's end-effector frame, from ``F_T_EE``).
Neither library is imported here.
"""

from __future__ import annotations

import numpy as np

from robot.arm import rot_z
from robot.executor import Outcome

#: libfranka errors hydo recovers from automatically (at most once per primitive, three times per
#: episode): reflexes, communication hiccups and motion-generator discontinuities.
RECOVERABLE_ERRORS = frozenset(
    {
        "cartesian_reflex",
        "joint_reflex",
        "communication_constraints_violation",
        "cartesian_motion_generator_acceleration_discontinuity",
        "cartesian_motion_generator_joint_acceleration_discontinuity",
        "cartesian_motion_generator_joint_velocity_discontinuity",
        "cartesian_motion_generator_velocity_discontinuity",
        "controller_torque_discontinuity",
        "joint_motion_generator_acceleration_discontinuity",
        "joint_motion_generator_velocity_discontinuity",
    }
)
#: What the person must do for the errors that stop the run (anything not recoverable).
OPERATOR_ACTIONS = {
    "power_limit_violation": "check the arm's power supply and payload, then unlock the brakes in Desk",
    "joint_position_limits_violation": "guide the arm away from its joint limit in Desk, then re-run",
    "cartesian_position_limits_violation": "guide the arm back into its workspace in Desk, then re-run",
    "self_collision_avoidance_violation": "guide the arm out of self-collision in Desk, then re-run",
    "user_stop": "release the external activation/stop device once the cell is safe, then re-run",
    "tau_j_range_violation": "check payload and tool settings in Desk, then re-run",
    "instability_detected": "check the tool and payload settings in Desk, then re-run",
}


def classify_errors(errors: tuple[str, ...] | list[str]) -> Outcome:
    """``reflex`` when every active error is recoverable, ``critical`` otherwise (and for none)."""
    errors = tuple(errors)
    if errors and all(e in RECOVERABLE_ERRORS for e in errors):
        return Outcome.reflex
    return Outcome.critical


def operator_action(errors) -> str:
    """One sentence telling the person what to do about ``errors``."""
    for e in errors:
        if e in OPERATOR_ACTIONS:
            return OPERATOR_ACTIONS[e]
    return "inspect the arm and clear the error in Desk, then re-run"


def error_names(errors) -> tuple[str, ...]:
    """Names of the active flags of a libfranka ``Errors`` object."""
    if errors is None:
        return ()
    return tuple(
        sorted(n for n in dir(errors) if not n.startswith("_") and getattr(errors, n, False) is True)
    )


def fingertip_to_ee(cell, F_T_EE: np.ndarray) -> np.ndarray:
    """(4, 4) ``T_tip^-1 · T_EE`` in the flange frame: right-multiply a fingertip pose to get the EE pose."""
    F_T_tip = np.eye(4)
    F_T_tip[:3, :3] = rot_z(cell.hand_yaw)
    F_T_tip[:3, 3] = cell.fingertip_offset
    return np.linalg.inv(F_T_tip) @ F_T_EE
