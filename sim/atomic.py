"""The one home of "never half-written": every file hydo writes for keeps goes through here.

``sim`` is the package every other one imports (models, robot, hydo_cli, bench), so the helper lives
at this lowest layer. A write goes to a temporary file in the destination folder, is flushed and
fsync'ed, and is then moved over the destination with ``os.replace`` (atomic on POSIX); a crash
leaves either the old file or the new one, never a torn one, and at worst a stray ``.*.tmp``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import BinaryIO


def atomic_write(path: str | os.PathLike, write: Callable[[BinaryIO], None], mode: int = 0o644) -> Path:
    """Call ``write(file)`` on a temp file next to ``path``, then move it into place; returns path.

    ``mode``: permissions of the result (``mkstemp`` creates 0600; results are meant to be shared).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, mode)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    try:  # make the rename itself durable (best effort: not every filesystem allows it)
        dir_fd = os.open(path.parent, os.O_RDONLY)
    except OSError:
        return path
    try:
        os.fsync(dir_fd)
    except OSError:
        pass
    finally:
        os.close(dir_fd)
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically."""
    return atomic_write(path, lambda f: f.write(text.encode("utf-8")))
