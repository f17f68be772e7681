"""Shared fixtures: the repository paths, the paper's protocol, and a fixed-seed generator.

Parallel workers (pytest-xdist, ``scripts/test.sh`` runs ``-n``): each worker gets an X display
of its own (an Xvfb started here), because the scripted participant of ``facelab run
--simulate`` moves the one pointer of its display and two sessions on one screen would click
into each other's windows. Ports, databases and folders are per test already (port 0 or a free
port, temporary folders). Slow tests are collected first so that the long ones start early and
the short ones fill the gaps at the end.
"""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
KATO = ROOT / "protocols" / "kato2021.yaml"

_XVFB: subprocess.Popen | None = None


def _own_display() -> None:
    """Start an Xvfb for this worker and point DISPLAY (and every child) at it."""
    global _XVFB
    exe = shutil.which("Xvfb")
    if exe is None:
        return  # the display tests say so themselves
    read, write = os.pipe()
    _XVFB = subprocess.Popen(
        [exe, "-displayfd", str(write), "-screen", "0", "1280x1024x24", "-nolisten", "tcp"],
        pass_fds=(write,), stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
    )  # fmt: skip
    os.close(write)
    with os.fdopen(read) as fh:
        number = fh.readline().strip()
    if not number:
        raise RuntimeError("Xvfb did not start for this test worker")
    os.environ["DISPLAY"] = f":{number}"
    os.environ.pop("XAUTHORITY", None)  # no cookie: the worker's own server admits local clients


def pytest_configure(config: pytest.Config) -> None:
    # a facelab child that dies in native code (a signal, not an error) prints where it was
    os.environ.setdefault("PYTHONFAULTHANDLER", "1")
    if os.environ.get("PYTEST_XDIST_WORKER") and os.environ.get("DISPLAY"):
        _own_display()


def pytest_unconfigure(config: pytest.Config) -> None:
    if _XVFB is not None:
        _XVFB.terminate()
        _XVFB.wait(timeout=10)


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)  # stable: slow first


@pytest.fixture
def kato_path() -> Path:
    return KATO


@pytest.fixture
def kato_text() -> str:
    return KATO.read_text(encoding="utf-8")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20260101)
