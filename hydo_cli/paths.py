"""Output paths every command checks the same way, before any slow work runs."""

from __future__ import annotations

import os
from pathlib import Path

from hydo_cli.errors import HydoError


def check_writable(flag: str, path: Path | None) -> None:
    """Refuse, in one line, an output path that cannot be written (checked before any episode runs;
    missing folders are made when the file is written)."""
    if path is None:
        return
    if path.is_dir():
        raise HydoError(f"{flag} {path} is a folder: give a file name")
    ancestor = path.parent.absolute()
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise HydoError(f"{flag} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK) or (path.exists() and not os.access(path, os.W_OK)):
        raise HydoError(f"{flag} {path} is not writable")


def check_writable_folder(flag: str, path: Path | None) -> None:
    """Refuse, in one line, an output folder that cannot be made or written (checked before any work)."""
    if path is None:
        return
    if path.exists() and not path.is_dir():
        raise HydoError(f"{flag} {path} is a file, not a folder")
    ancestor = path.absolute()
    while not ancestor.exists():
        ancestor = ancestor.parent
    if not ancestor.is_dir():
        raise HydoError(f"{flag} {path}: {ancestor} is a file, not a folder")
    if not os.access(ancestor, os.W_OK):
        raise HydoError(f"{flag} {path} is not writable")
