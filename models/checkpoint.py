"""Checkpoint files: atomic writes, safe loads, one clear error.

A checkpoint is ``{"format_version": FORMAT_VERSION, "payload": payload}`` written with ``torch.save``;
the payload is plain data (state_dicts of tensors, numbers, strings, lists, dicts) so it loads with
``torch.load(weights_only=True)``, which never executes pickled code.

Writes go to a temporary file in the same directory, are fsync'ed and then ``os.replace``d over the
target, so a crash mid-write leaves the previous checkpoint intact, never a truncated one.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path
from typing import Any

import torch

from sim.atomic import atomic_write

#: Bump when the checkpoint layout changes; files of another version are refused, not patched.
FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint is missing, unreadable (truncated / corrupt) or of another format version.

    ``CheckpointError(path, reason)`` gives the one-line message ``checkpoint PATH: reason`` and keeps
    ``path``; ``CheckpointError(message)`` takes a ready message (``path`` is then None).
    """

    def __init__(self, path: str | os.PathLike, reason: str | None = None) -> None:
        if reason is None:  # CheckpointError("whole message")
            self.path = None
            super().__init__(str(path))
        else:
            self.path = Path(path)
            super().__init__(f"checkpoint {self.path}: {reason}")


def save_checkpoint(path: str | os.PathLike, payload: dict[str, Any]) -> None:
    """Write ``payload`` to ``path`` atomically (temp file in the same dir + fsync + ``os.replace``)."""
    atomic_write(path, lambda f: torch.save({"format_version": FORMAT_VERSION, "payload": payload}, f))


def load_checkpoint(path: str | os.PathLike) -> dict[str, Any]:
    """Read the payload written by :func:`save_checkpoint`; raise :class:`CheckpointError` otherwise."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(path, "no such file")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except (RuntimeError, EOFError, OSError, ValueError, pickle.UnpicklingError, zipfile.BadZipFile) as e:
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        detail = f" ({type(e).__name__}: {first[:120]})" if first else f" ({type(e).__name__})"
        raise CheckpointError(path, f"truncated or corrupt, cannot be read{detail}") from e
    if not isinstance(data, dict) or "format_version" not in data or "payload" not in data:
        raise CheckpointError(path, "not a hydo checkpoint (no format_version / payload)")
    version = data["format_version"]
    if version != FORMAT_VERSION:
        raise CheckpointError(
            path,
            f"format version {version}, this hydo reads version {FORMAT_VERSION}; retrain or use a matching hydo",
        )
    return data["payload"]
