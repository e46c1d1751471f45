"""The session folder: every observation, decision and command of a deploy run, SIGKILL-safe.

Layout::

    SESSION/
      session.json        command line, robot, model manifest, cell summary, versions (written first)
      cell.yaml           the cell file as loaded
      background.npz      the empty-bin background in use
      goals/eNNN.npz      each episode's goal cloud
      log.jsonl           one JSON object per line: events, plans, commands, outcomes, metrics
      steps/eNNN-sNN.npz  per observation: depth per camera, masks, clouds, observation, action, plan

``log.jsonl`` lines are written, flushed and fsynced one at a time, and a ``command`` line is
written *before* the command goes to the robot: after a crash (even SIGKILL) the file parses up to
its last complete line and its last ``command`` line is the last motion the robot may have
received. :func:`read_log` reads it back that way. The replay camera (``robot.cameras``) plays the
``steps/`` depth frames back.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path

import numpy as np

DEPTH_SCALE_M = 1e-4  # depth is stored as uint16 in units of 0.1 mm (0 = hole, max 6.5 m)


def _jsonable(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, Path):
        return str(v)
    raise TypeError(f"not JSON serialisable: {type(v).__name__}")


class SessionLog:
    """Append-only JSONL log plus per-step arrays in a session folder."""

    def __init__(self, folder: str | Path):
        self.folder = Path(folder)
        if self.folder.exists() and any(self.folder.iterdir()):
            raise FileExistsError(f"session folder {self.folder} is not empty: choose a new --log folder")
        (self.folder / "steps").mkdir(parents=True, exist_ok=True)
        (self.folder / "goals").mkdir(exist_ok=True)
        self.path = self.folder / "log.jsonl"
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        self.n_lines = 0

    def event(self, name: str, /, **fields) -> None:
        """Write one line ``{"t", "event": name, **fields}`` and fsync it before returning."""
        if self._fd is None:
            return
        line = json.dumps({"t": round(time.time(), 6), "event": name, **fields}, default=_jsonable)
        os.write(self._fd, (line + "\n").encode())
        os.fsync(self._fd)
        self.n_lines += 1

    def command(self, robot: str, command) -> None:
        """The line that must precede every motion command."""
        self.event("command", robot=robot, **command.to_json())

    def write_json(self, name: str, data: dict) -> Path:
        path = self.folder / name
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(data, indent=2, default=_jsonable))
        tmp.replace(path)
        return path

    def save_step(self, episode: int, step: int, frames, **arrays) -> Path:
        """``steps/eNNN-sNN.npz``: depth per camera (``depth/SERIAL``, uint16 0.1 mm) + arrays."""
        out = {}
        for f in frames:
            d = np.nan_to_num(np.asarray(f.depth, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0)
            d = np.round(d / DEPTH_SCALE_M)
            d[(d < 0) | (d > 65535)] = 0  # out of the format's range: a hole, never a clipped depth
            out[f"depth/{f.serial}"] = d.astype(np.uint16)
            out[f"timestamp/{f.serial}"] = np.array(f.timestamp)
        for k, v in arrays.items():
            if v is not None:
                out[k] = np.asarray(v)
        path = self.folder / "steps" / f"e{episode:03d}-s{step:02d}.npz"
        tmp = path.with_name(f".{path.stem}.tmp.npz")
        np.savez_compressed(tmp, **out)
        tmp.replace(path)
        return path

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    def __enter__(self) -> SessionLog:
        return self

    def __exit__(self, *exc) -> bool:
        self.close()
        return False


def session_folders(path: str | Path) -> list[Path]:
    """``path`` if it is a session folder (it has ``log.jsonl``); else the session folders right inside
    it, in name order (a ladder rung whose episodes ran as several sessions: ``e000-049``, ...)."""
    path = Path(path)
    if (path / "log.jsonl").is_file():
        return [path]
    if not path.is_dir():
        return []
    return sorted(p for p in path.iterdir() if (p / "log.jsonl").is_file())


def read_log(path: str | Path) -> list[dict]:
    """Parse ``log.jsonl`` up to its last complete line (a torn last line after a crash is skipped)."""
    path = Path(path)
    if path.is_dir():
        path = path / "log.jsonl"
    out = []
    for line in path.read_bytes().split(b"\n"):
        if not line.strip():
            continue
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            break  # the torn last line of a killed process
    return out


def load_depth(npz, serial: str) -> np.ndarray:
    """Depth (H, W) float32 metres of ``serial`` from a step file opened with ``np.load``."""
    return npz[f"depth/{serial}"].astype(np.float32) * DEPTH_SCALE_M
