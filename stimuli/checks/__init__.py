"""Stimulus checks: every clip measured before a participant sees it (``facelab check`` and
the end of every render command). :mod:`.avatar_checks` audits the avatar's geometry,
:mod:`.face_tracker` runs an outside face tracker (MediaPipe, its own environment) on the
decoded frames, :mod:`.clip_checks` turns what it measured into rows, and :mod:`.run_checks`
writes ``stimulus_checks.csv``."""

from facelab.stimuli.checks.rows import CHECK_COLUMNS, CheckRow
from facelab.stimuli.checks.run_checks import CHECKS_NAME, CheckReport, check_clips

__all__ = ["CHECKS_NAME", "CHECK_COLUMNS", "CheckReport", "CheckRow", "check_clips"]
