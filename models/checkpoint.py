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


def load_replay(path: str | os.PathLike, n_obj: int, n_bg: int):
    """``ReplayBuffer.load`` behind a check of the file against the buffer's own layout.

    A run's ``replay.npz`` is written with its checkpoint; on ``--resume`` a damaged one (zero bytes,
    truncated, random bytes, missing keys, arrays whose shapes disagree with each other, with ``meta``
    or with the run's point counts ``n_obj`` / ``n_bg``) raises :class:`CheckpointError`, one line
    naming the file, instead of numpy's ``EOFError`` / ``BadZipFile`` / ``ValueError`` traceback or a
    silently short buffer.
    """
    import ast

    from models.replay import REQUIRED_ARRAYS, ReplayBuffer

    path = Path(path)

    def bad(reason: str) -> CheckpointError:
        return CheckpointError(f"replay {path}: {reason}; the run cannot resume with it")

    arrays = _read_npz(path, bad)
    capacity, m_obj, m_bg, pos, full = _check_members(arrays, REQUIRED_ARRAYS, "replay", bad)
    if (m_obj, m_bg) != (n_obj, n_bg):
        raise bad(f"holds {m_obj}+{m_bg} points per observation, the run's config says {n_obj}+{n_bg}")
    n = len(arrays["points"]) if arrays["points"].ndim else -1
    if capacity < 1 or not 0 <= pos < capacity or full not in (0, 1) or n != (capacity if full else pos):
        raise bad(
            f"`meta` (capacity {capacity}, position {pos}, full {full}) disagrees with {n} stored transitions"
        )
    _check_layout(arrays, ReplayBuffer._ARRAYS, n, n_obj, n_bg, bad)
    try:
        ast.literal_eval(bytes(arrays["rng"]).decode())
        return ReplayBuffer.from_arrays(arrays)  # the members read once, above
    except (ValueError, SyntaxError, TypeError, KeyError, UnicodeDecodeError, MemoryError) as e:
        raise bad(f"unreadable contents ({type(e).__name__})") from None


def _check_members(arrays: dict, required, what: str, bad) -> tuple[int, int, int, int, int]:
    """The ``required`` members are there and ``meta`` is 5 integers: ``(capacity, n_obj, n_bg, pos,
    full)``."""
    missing = [k for k in required if k not in arrays]
    if missing:
        raise bad(f"lacks {missing} (not a hydo {what}?)")
    meta = arrays["meta"]
    if meta.shape != (5,) or meta.dtype.kind not in "iu":
        raise bad(f"`meta` must be 5 integers, got {meta.dtype} of shape {meta.shape}")
    return tuple(int(v) for v in meta)


def _check_layout(arrays: dict, keys, n: int, n_obj: int, n_bg: int, bad) -> None:
    """Each of ``keys`` present in ``arrays`` holds ``n`` rows of the buffer's own per-transition shape
    and dtype kind, and ``index`` lies among the object points."""
    from models.replay import ReplayBuffer

    layout = ReplayBuffer(1, n_obj, n_bg)  # the buffer's own per-transition shapes and dtype kinds
    for k in keys:
        if k not in arrays:
            continue
        a, want = arrays[k], getattr(layout, k)
        if a.shape != (n, *want.shape[1:]):
            raise bad(f"`{k}` has shape {a.shape}, expected {(n, *want.shape[1:])}")
        if a.dtype.kind != want.dtype.kind and not (a.dtype.kind in "iu" and want.dtype.kind in "iu"):
            raise bad(f"`{k}` is {a.dtype}, expected {want.dtype}")
    if n and not (0 <= arrays["index"].min() and arrays["index"].max() < n_obj):
        raise bad(f"`index` must lie in [0, {n_obj}) (object points)")


def _read_npz(path: Path, bad) -> dict:
    """Every member of the ``.npz`` at ``path`` (no pickles), or ``bad(reason)`` raised."""
    import zlib

    import numpy as np

    if not path.is_file():
        raise bad("no such file")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):
            raise bad("a single .npy array, not an .npz archive")
        with z:  # read every member now: a truncated member fails here, with the file's name
            return {k: np.asarray(z[k]) for k in z.files}
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        what = "empty file (0 bytes)" if path.stat().st_size == 0 else "truncated or not an .npz archive"
        raise bad(f"{what} ({type(e).__name__})") from None


def apply_replay_segment(buffer, path: str | os.PathLike) -> None:
    """Check the replay segment at ``path`` (``ReplayBuffer.save_segment``) against ``buffer``'s layout
    and apply it; a damaged or foreign one raises :class:`CheckpointError`, one line naming the file."""
    import ast

    from models.replay import SEGMENT_ARRAYS, SEGMENT_OPTIONAL

    path = Path(path)

    def bad(reason: str) -> CheckpointError:
        return CheckpointError(f"replay segment {path}: {reason}; the run cannot resume with it")

    arrays = _read_npz(path, bad)
    capacity, m_obj, m_bg, pos, full = _check_members(arrays, SEGMENT_ARRAYS, "replay segment", bad)
    slots, links = arrays["slots"], arrays["next_slot"]
    if (capacity, m_obj, m_bg) != (buffer.capacity, buffer.n_obj, buffer.n_bg):
        raise bad(
            f"is for a buffer of {capacity} transitions at {m_obj}+{m_bg} points, the run's holds "
            f"{buffer.capacity} at {buffer.n_obj}+{buffer.n_bg}"
        )
    if not 0 <= pos < capacity or full not in (0, 1):
        raise bad(f"`meta` position {pos} / full {full} is outside the buffer")
    if slots.ndim != 1 or slots.dtype.kind not in "iu" or len(slots) > capacity:
        raise bad(f"`slots` must be at most {capacity} integers, got {slots.dtype} of shape {slots.shape}")
    if len(slots) and not (0 <= slots.min() and slots.max() < capacity):
        raise bad(f"`slots` must lie in [0, {capacity})")
    if links.shape != (capacity,) or links.dtype.kind not in "iu" or (links.size and links.min() < -1):
        raise bad(f"`next_slot` must be {capacity} slots or -1")
    if links.size and links.max() >= capacity:
        raise bad(f"`next_slot` must lie in [-1, {capacity})")
    _check_layout(
        arrays, (*SEGMENT_ARRAYS[5:], *SEGMENT_OPTIONAL), len(slots), buffer.n_obj, buffer.n_bg, bad
    )
    try:
        ast.literal_eval(bytes(arrays["rng"]).decode())
        buffer.apply_segment(arrays)
    except (ValueError, SyntaxError, TypeError, KeyError, UnicodeDecodeError) as e:
        raise bad(f"unreadable contents ({type(e).__name__})") from None
