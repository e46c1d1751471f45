"""Deploy-side errors: each is reported by ``hydo`` as one line with a non-zero exit, before any motion."""


class RobotError(Exception):
    """Base of every deploy failure (bad model, camera, segmentation, registration, plan, robot)."""


class ModelLoadError(RobotError):
    """An exported model folder that must not be run: missing/corrupt file, hash or contract mismatch."""


class InputError(RobotError):
    """An observation or policy output that breaks the contract (shape, NaN), named in the message."""
