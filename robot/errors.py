"""Deploy-side errors: each is reported by ``hydo`` as one line with a non-zero exit, before any motion."""


class RobotError(Exception):
    """Base of every deploy failure (bad model, camera, segmentation, registration, plan, robot)."""


class ModelLoadError(RobotError):
    """An exported model folder that must not be run: missing/corrupt file, hash or contract mismatch."""


class InputError(RobotError):
    """An observation or policy output that breaks the contract (shape, NaN), named in the message."""


# --- deploy (cell, cameras, perception, registration, plan, robot) ---------------------------------
# Each subclass names one failure family; ``hydo`` prints its message as one line and exits 1.


class CellError(RobotError):
    """A cell file (``cell.yaml``) that must not be used: missing key, bad value, unsafe limits."""


class GoalError(RobotError):
    """A goal the cell cannot hold (outside the bin or the workspace): a wrong goal file or
    ``--goal-offset``, refused before any motion. Not a per-step refusal: it stops the run."""


class CameraError(RobotError):
    """A camera that is missing, has the wrong serial or link, times out, or delivers stale frames."""


class PerceptionError(RobotError):
    """A capture that cannot become an observation: empty mask, NaN depth, background mismatch."""


class RegistrationError(RobotError):
    """The object cloud could not be registered to the goal cloud well enough to act on."""


class UnreachableError(RobotError):
    """A plan the arm's kinematics cannot follow (no IK solution, or a joint within the limit margin)."""


class RobotConnectionError(RobotError):
    """The robot is absent or the connection was lost; hydo never reconnects and continues silently."""


class RobotFaultError(RobotError):
    """A robot error that stops the run (critical fault, a reflex that would not clear, too many reflexes)."""


class RecoveryLimitError(RobotFaultError):
    """A recoverable reflex beyond the automatic-recovery limits (robot-safety.md: at most one recovery
    per primitive, three per episode): a real arm stops the run here."""


class RealtimeKernelError(RobotError):
    """No realtime kernel for a real arm and no explicit override."""
