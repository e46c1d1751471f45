"""The errors hydo reports as one line and a non-zero exit, never a traceback (``main.main``).

Each library package raises its own precise exception (``ObjectMeshError`` in ``sim.objects``,
``PrimitiveRejected`` in ``sim.primitive``, ``CheckpointError`` in ``models.checkpoint``, ...);
``known_errors()`` lists them for ``main`` to catch. Unknown exceptions still raise with a traceback,
so real bugs are never hidden behind a friendly message.
"""

from __future__ import annotations


class HydoError(Exception):
    """A user-facing failure: bad input, missing file, refused plan. The message is the whole story."""


def known_errors() -> tuple[type[BaseException], ...]:
    """Exception types that ``main`` turns into one stderr line; imported lazily (torch is optional)."""
    from sim.objects import ObjectMeshError
    from sim.primitive import PrimitiveRejected

    errors: list[type[BaseException]] = [HydoError, ObjectMeshError, PrimitiveRejected]
    try:
        from models.checkpoint import CheckpointError

        errors.append(CheckpointError)
    except ImportError:  # deploy installs have no torch
        pass
    try:
        from robot.errors import RobotError

        errors.append(RobotError)
    except ImportError:
        pass
    return tuple(errors)
