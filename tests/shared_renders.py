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
from pathlib import Path

import pytest

from facelab.experiment.cli import main

__all__ = ["rendered_clips"]


def _run_root(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder this run's workers share (pytest-xdist gives each ``<run>/popen-gwN``)."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base


def rendered_clips(
    tmp_path_factory: pytest.TempPathFactory,
    *,
    text: str,
    into: Path,
    name: str,
    size: str,
    fps: str,
) -> Path:
    """Write the protocol ``text`` to ``into/name`` and its clips - rendered at ``size``
    (WxH) and ``fps`` - to ``into/clips``, exactly as ``facelab render`` writes them; the
    render runs once per test run for each text and options. The text may name no file of its
    own (the render reads it elsewhere; nothing it writes depends on the file's name or
    folder). Returns the clips folder."""
    args = ("--size", size, "--fps", fps)
    key = hashlib.sha256("\0".join((text, *args)).encode("utf-8")).hexdigest()[:16]
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
            argv = ["render", str(work / "protocol.yaml"), "--out", str(work / "clips"), *args,
                    "--quiet"]  # fmt: skip
            assert main(argv) == 0
            work.rename(done)
    (into / name).write_text(text, encoding="utf-8")
    shutil.copytree(done / "clips", into / "clips")
    return into / "clips"
