"""Files written so that a crash never leaves half of one: a temporary file in the same folder,
fsynced, renamed over the target, and the folder fsynced (the bottom layer: no facelab imports).
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["fsync_dir", "replace_file"]


def fsync_dir(folder: Path) -> None:
    """fsync a directory, so that files created or renamed in it survive a power cut."""
    fd = os.open(folder, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def replace_file(path: Path, data: str | bytes) -> None:
    """Write ``data`` (text as UTF-8) to ``path`` atomically. The temporary name is unique to
    this process and call (``.<name>.<pid>.<random>.part``), so two processes writing the same
    file never share one; it is removed if the write fails."""
    path = Path(path)
    part = path.with_name(f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}.part")
    try:
        with open(part, "wb") as fh:
            fh.write(data.encode("utf-8") if isinstance(data, str) else data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)
    fsync_dir(path.parent)
