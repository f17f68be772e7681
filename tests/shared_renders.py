"""Renders shared by a whole test run: one ``facelab render`` of a protocol text with given
options, whichever test module (on whichever pytest-xdist worker) needs it first.

Several modules render the same short study (the online, lab-window and VR sessions). Each
used to render it in its own module fixture, once on every worker its tests ran on. The
first caller now renders it into a folder of the run's base temporary directory, under a
file lock (``flock``: the others wait, then find it done); every caller gets a copy of the
clips, so a test that changes its clips changes nobody else's.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytest

from facelab.experiment.cli import main

__all__ = ["remember_factory", "rendered_clips"]

_factory: list[pytest.TempPathFactory] = []  # this process's, from tests/conftest.py


def remember_factory(tmp_path_factory: pytest.TempPathFactory) -> None:
    """The session's temporary-path factory, for callers that are not handed one."""
    _factory[:] = [tmp_path_factory]


def _run_root(tmp_path_factory: pytest.TempPathFactory | None) -> Path:
    """The folder this run's workers share (pytest-xdist gives each ``<run>/popen-gwN``)."""
    base = (tmp_path_factory or _factory[0]).getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def rendered_clips(
    tmp_path_factory: pytest.TempPathFactory | None,
    *,
    text: str,
    into: Path,
    name: str,
    size: str,
    fps: str,
    files: Mapping[str, bytes] | None = None,
    extra: Sequence[str] = (),
    clips: str = "clips",
) -> Path:
    """Write the protocol ``text`` to ``into/name`` and its clips - rendered at ``size``
    (WxH) and ``fps`` - to ``into/<clips>``, exactly as ``facelab render`` writes them; the
    render runs once per test run for each text, files and options. ``files`` (name ->
    bytes: an avatar the text names) are written beside the protocol for the render (and the
    caller's own copies are its own business); ``extra`` are more render options
    (``--accept-check``). Nothing the render writes may depend on the protocol file's name or
    folder. Returns the clips folder."""
    args = ("--size", size, "--fps", fps, *extra)
    files = dict(files or {})
    hashes = [f"{k}={hashlib.sha256(v).hexdigest()}" for k, v in sorted(files.items())]
    parts = [text, *args, *hashes]
    key = hashlib.sha256("\0".join(parts).encode("utf-8")).hexdigest()[:16]
    shared = _run_root(tmp_path_factory) / "shared-renders"
    shared.mkdir(exist_ok=True)
    done = shared / key
    with open(shared / f"{key}.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file is closed
        if not done.is_dir():
            work = shared / f"{key}.partial"  # a render that failed half-way is started again
            shutil.rmtree(work, ignore_errors=True)
            work.mkdir()
            (work / "protocol.yaml").write_text(text, encoding="utf-8")
            for file_name, data in files.items():
                (work / file_name).write_bytes(data)
            argv = ["render", str(work / "protocol.yaml"), "--out", str(work / "clips"), *args,
                    "--quiet"]  # fmt: skip
            assert main(argv) == 0
            work.rename(done)
    (into / name).write_text(text, encoding="utf-8")
    shutil.copytree(done / "clips", into / clips)
    return into / clips
