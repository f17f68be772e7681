"""One error hierarchy for facelab (the bottom layer: imports nothing else of facelab).

Every error a user can cause derives from :class:`FacelabError`; the command line turns
them into one clear message and its ``exit_code`` (2 for a mistake in the input). Anything
else is a bug and keeps its traceback::

    FacelabError                   exit 2
    ├── ProtocolError              a protocol file: every problem, each with file:line
    ├── StageError                 a stage was given input it cannot use
    │   ├── AvatarError            an avatar file or mesh
    │   ├── SpeechError            audio or text for a speech stimulus
    │   ├── VisemeError            input of the viseme analyser
    │   └── SessionError           a participant session cannot start or continue
    ├── AnalysisError              data that cannot be analysed as asked
    └── SessionAbortedError        exit 4: the experimenter stopped a session (data kept)
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

__all__ = [
    "AnalysisError",
    "AvatarError",
    "BehaviourError",
    "FacelabError",
    "FormatError",
    "Issue",
    "ProtocolError",
    "SessionAbortedError",
    "SessionError",
    "SpeechError",
    "StageError",
    "VisemeError",
]


class FacelabError(Exception):
    """Base class: a problem caused by user input (files, options, data)."""

    exit_code = 2


class StageError(FacelabError):
    """A stage (render, run, analyse …) was given input it cannot use."""


class AvatarError(StageError):
    """An avatar file or mesh that facelab cannot use."""


class BehaviourError(StageError):
    """A behaviour library, annotation table, emotion or plan that cannot be used."""


class SpeechError(StageError):
    """Audio or text that cannot be turned into a speech stimulus."""


class VisemeError(StageError):
    """Input the viseme stage cannot use."""


class SessionError(StageError):
    """A participant session cannot start or continue as asked (clips, lock, log)."""


class FormatError(StageError):
    """A file one stage wrote for another (clip manifest, behaviour log, model header) that
    cannot be read."""


class AnalysisError(FacelabError):
    """The data cannot be analysed as asked (missing columns, cells, too few levels…)."""


class SessionAbortedError(FacelabError):
    """The experimenter stopped the session; every response given so far is saved."""

    exit_code = 4


@dataclass(frozen=True)
class Issue:
    """One problem found in a protocol file.

    ``path`` is the key path inside the document, e.g. ``("conditions", 1, "params", "gain")``;
    ``line`` is 1-based, or ``None`` when the problem is not tied to a line.
    """

    path: tuple[str | int, ...]
    message: str
    line: int | None = None

    def dotted(self) -> str:
        out = ""
        for part in self.path:
            out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
        return out or "(document)"


class ProtocolError(FacelabError):
    """A protocol file is unreadable or invalid. Holds every problem found, each with its line."""

    def __init__(self, file: Path | str, issues: Sequence[Issue]):
        self.file = Path(file)
        self.issues = list(issues)
        super().__init__(self._format())

    def _format(self) -> str:
        lines = [
            f"{self.file}: invalid protocol ({len(self.issues)} problem"
            f"{'' if len(self.issues) == 1 else 's'})"
        ]
        for issue in self.issues:
            where = f"{self.file}:{issue.line}" if issue.line else f"{self.file}"
            lines.append(f"  {where}: {issue.dotted()}: {issue.message}")
        return "\n".join(lines)
