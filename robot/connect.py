"""Building the devices of a deploy run: the executor for ``--robot`` and the cameras of the cell.

One place chooses between the real arm libraries, the MuJoCo twin and recorded sessions, so the
executor and camera modules never import each other or the twin: :func:`make_executor` imports
``robot.panda`` (panda-python), ``robot.fr3`` (franky) or ``robot.twin`` (MuJoCo) only when that
robot is selected, and :func:`open_cameras` builds RealSense, twin or replay cameras.
"""

from __future__ import annotations

from pathlib import Path

from robot.cameras import CameraSet, RealSenseCamera, ReplayCamera
from robot.executor import Executor


def make_executor(
    kind: str, cell, log=None, world=None, allow_no_realtime: bool = False, speed_scale: float = 1.0
) -> Executor:
    """The executor for ``--robot kind``; robot libraries are imported only here, only when chosen."""
    if kind == "sim":
        from robot.twin import TwinExecutor

        if world is None:
            raise ValueError("the sim executor needs the twin world it drives")
        return TwinExecutor(world, cell, log=log, speed_scale=speed_scale)
    if kind == "panda":
        from robot.panda import PandaExecutor

        return PandaExecutor(cell, log=log, allow_no_realtime=allow_no_realtime, speed_scale=speed_scale)
    if kind == "fr3":
        from robot.fr3 import FR3Executor

        return FR3Executor(cell, log=log, allow_no_realtime=allow_no_realtime, speed_scale=speed_scale)
    raise ValueError(f"`--robot` must be one of ['panda', 'fr3', 'sim']. Got {kind!r}.")


def open_cameras(cell, kind: str, world=None, replay: str | Path | None = None) -> CameraSet:
    """The cameras of ``cell`` for ``--robot kind`` (not yet opened: use ``with``)."""
    if replay is not None:
        return CameraSet([ReplayCamera(spec, replay) for spec in cell.cameras])
    if kind == "sim":
        from robot.twin import TwinCamera

        return CameraSet([TwinCamera(world, spec, i) for i, spec in enumerate(cell.cameras)])
    return CameraSet([RealSenseCamera(spec, cell.perception.warmup_frames) for spec in cell.cameras])
