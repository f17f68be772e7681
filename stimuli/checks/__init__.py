"""Stimulus checks: every clip measured before a participant sees it (``facelab check`` and
the end of every render command). :mod:`.avatar_checks` audits the avatar's geometry,
:mod:`.face_tracker` runs an outside face tracker (MediaPipe, its own environment) on the
decoded frames, :mod:`.clip_checks` turns what it measured into rows, and :mod:`.run_checks`
writes ``stimulus_checks.csv``."""

from __future__ import annotations

from typing import Any

from facelab.stimuli.checks.rows import CHECK_COLUMNS, CheckRow

__all__ = ["CHECKS_NAME", "CHECK_COLUMNS", "CheckReport", "CheckRow", "check_clips"]


def __getattr__(name: str) -> Any:
    """:mod:`.run_checks` (the renderer and the clip decoders) is loaded on first use, so
    auditing an avatar (``facelab validate``) does not load pyrender."""
    if name in ("CHECKS_NAME", "CheckReport", "check_clips"):
        from facelab.stimuli.checks import run_checks

        return getattr(run_checks, name)
    raise AttributeError(f"module 'facelab.stimuli.checks' has no attribute {name!r}")
