"""Session logs: one row per response, appended and fsync'd the moment it is given.

Layout (BIDS-style, one folder per participant session)::

    results/<study>/sub-<ID>/ses-<N>/
        sub-<ID>_ses-<N>_task-<study>_beh.tsv       the responses (this module appends to it)
        sub-<ID>_ses-<N>_task-<study>_beh.json      data dictionary of the TSV columns
        sub-<ID>_ses-<N>_task-<study>_session.json  provenance: protocol hash, seed, trial
                                                    order, clip hashes, software, screen/audio
        sub-<ID>_ses-<N>_task-<study>_playback.jsonl  every flip of every clip (the runner)
        sub-<ID>_ses-<N>_task-<study>_screen_poses.jsonl  VR: head and controller poses while
                                                    each screen waited for an answer (online)
        sub-<ID>_ses-<N>_task-<study>_actions.jsonl   what a scripted participant did (--simulate)
        sub-<ID>_ses-<N>_task-<study>_staircase.jsonl every step of every staircase
        sub-<ID>_ses-<N>_task-<study>_repairs.tsv   only after a crash: cut-off lines kept verbatim
        .lock                                       held (flock) while a process writes the session

Rules:

* a session folder that holds a log is never overwritten (:meth:`SessionLog.create` refuses);
  :meth:`SessionLog.resume` reopens it;
* every row is written with one ``write`` and ``fsync``'d before :meth:`SessionLog.append`
  returns, with SIGINT/SIGTERM/SIGHUP held back for that moment, so a signal never tears a
  line; the folder is fsync'd after a file is created or replaced, so a new file survives a
  power cut too;
* a last line cut off mid-write (no newline, e.g. power loss) is detected on resume: if it
  still parses as a complete row it is kept, otherwise it is moved verbatim to the repairs
  file and that response is asked again - never silently dropped or duplicated;
* one writer: :class:`SessionLock` takes an exclusive ``flock`` on the session's ``.lock``;
  the kernel releases it when the process ends, however it ends, so a crash leaves no stale
  lock;
* every row carries its provenance: ``simulated`` and ``protocol_sha256``.

Missing values are written ``n/a``, as BIDS does. Logs written by facelab 0.1 (17 columns,
no provenance columns) are read (:data:`LOG_COLUMNS_V1`) but not continued; logs begun before
typed answers (:data:`LOG_COLUMNS_V2`, no ``score``) are read and continued in their own
columns (an answer with a score is refused there).
"""

from __future__ import annotations

import contextlib
import csv
import datetime as dt
import io
import json
import math
import os
import re
import signal
import socket
from collections.abc import Iterable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facelab.durable import fsync_dir, replace_file
from facelab.errors import SessionError, StageError

__all__ = [
    "COLUMN_DESCRIPTIONS",
    "LOG_COLUMNS",
    "LOG_COLUMNS_V1",
    "LOG_COLUMNS_V2",
    "MAX_SESSION",
    "NA",
    "SessionContext",
    "SessionLock",
    "SessionLog",
    "SessionPaths",
    "append_jsonl",
    "fsync_dir",
    "log_identity",
    "parse_log_text",
    "response_row",
    "rows_to_tsv",
    "session_paths",
    "utc_now",
]

#: Sessions are numbered 1..MAX_SESSION.
MAX_SESSION = 9999

#: The columns of facelab 0.1 logs (read only).
LOG_COLUMNS_V1: tuple[str, ...] = (
    "study",
    "participant",
    "session",
    "trial_index",
    "block",
    "set_index",
    "stimulus_set",
    "stimulus",
    "condition",
    "repetition",
    "item",
    "rating",
    "rating_start",
    "rt_s",
    "clip_onset",
    "clip_frames_dropped",
    "timestamp",
)

#: The columns of facelab logs before typed answers (no ``score``): read and continued.
LOG_COLUMNS_V2: tuple[str, ...] = (
    *LOG_COLUMNS_V1,
    "screen",
    "response",
    "correct",
    "level",
    "comparison",
    "position",
    "simulated",
    "protocol_sha256",
)

#: The columns written today: DESIGN.md's contract first, then the task and provenance columns.
LOG_COLUMNS: tuple[str, ...] = (
    *LOG_COLUMNS_V2[: LOG_COLUMNS_V2.index("correct") + 1],
    "score",
    *LOG_COLUMNS_V2[LOG_COLUMNS_V2.index("correct") + 1 :],
)

COLUMN_DESCRIPTIONS: dict[str, dict[str, str]] = {
    "study": {"Description": "Study id from the protocol."},
    "participant": {"Description": "Participant id (letters and digits)."},
    "session": {"Description": "Session number, from 1."},
    "trial_index": {"Description": "Position of the trial in the session's design, from 1; "
                    "0 for the sickness questionnaire (screen ssq), outside the design."},
    "block": {"Description": "Block id from the protocol (ssq for the sickness "
              "questionnaire)."},
    "set_index": {"Description": "Set number within the block, from 1 (0 for the sickness "
                  "questionnaire)."},
    "stimulus_set": {"Description": "Stimulus set id."},
    "stimulus": {"Description": "Stimulus id within the set (ssq: the symptom)."},
    "condition": {"Description": "Condition id (for a forced choice: the test condition; "
                  "ssq: before or after, when the questionnaire was given)."},
    "repetition": {"Description": "Nth showing of this stimulus and condition within the set."},
    "item": {"Description": "Response item id (VAS item, choice question or label question)."},
    "rating": {
        "Description": "The confirmed VAS position; n/a for choice screens.",
        "Units": "scale points (0 = left anchor)",
    },
    "rating_start": {
        "Description": "Marker position shown before the first click; n/a when the "
        "marker is hidden until the first click."
    },
    "rt_s": {
        "Description": "Time from the response screen appearing to the response.",
        "Units": "s",
    },
    "clip_onset": {
        "Description": "Flip time of the (first) clip's first frame on the session clock.",
        "Units": "s",
    },
    "clip_frames_dropped": {"Description": "Frames of the clip(s) shown late (dropped)."},
    "timestamp": {"Description": "Wall-clock time the response was confirmed (ISO 8601, UTC)."},
    "screen": {
        "Description": "Screen type that took the response: vas, choice_2afc, identify, "
        "typed, matrix (a word matrix), ssq (the Simulator Sickness Questionnaire) or a "
        "screen kind added by a package."
    },
    "response": {
        "Description": "Choice screens: the chosen condition id (2AFC) or label id (identify); "
        "typed screens: the text as typed (n/a when nothing was typed); matrix: the words "
        "picked, one per column, joined by spaces; ssq: the "
        "symptom's rating, 0 none, 1 slight, 2 moderate, 3 severe; n/a on VAS screens."
    },
    "correct": {
        "Description": "1 when the response is the correct one (2AFC: the test condition was "
        "chosen; identify: the true label; typed: every scoring unit reproduced; matrix: "
        "every word), 0 when not, n/a when the task has no correct answer."
    },
    "score": {
        "Description": "Typed answers: the share of the scoring units (keywords or morae of "
        "what was said) the answer reproduced, as pronounced; matrix: the share of the "
        "columns whose pick is the word said; n/a on other screens.",
        "Units": "proportion (0..1)",
    },
    "level": {"Description": "The stimulus level of the condition (a graded dimension), or n/a."},
    "comparison": {"Description": "2AFC: the standard condition the test was compared with."},
    "position": {"Description": "2AFC: where the test condition was shown, 1 (first/left) or 2."},
    "simulated": {"Description": "true when a simulated participant gave the response."},
    "protocol_sha256": {"Description": "SHA-256 of the protocol file the session ran."},
}

_INT_COLUMNS = {
    "session",
    "trial_index",
    "set_index",
    "repetition",
    "clip_frames_dropped",
    "correct",
    "position",
}
_FLOAT_COLUMNS = {"rating", "rating_start", "rt_s", "clip_onset", "level", "score"}
_BOOL_COLUMNS = {"simulated"}
NA = "n/a"
_HELD_SIGNALS = {signal.SIGINT, signal.SIGTERM, signal.SIGHUP}


@dataclass(frozen=True)
class SessionPaths:
    folder: Path
    tsv: Path
    dictionary: Path
    provenance: Path
    repairs: Path
    playback: Path
    actions: Path
    staircase: Path
    lock: Path
    screen_poses: Path


#: a response log's file name, as :func:`session_paths` makes it
_TSV_NAME = re.compile(
    r"^sub-(?P<participant>[A-Za-z0-9]+)_ses-(?P<session>\d+)_task-(?P<study>.+)_beh\.tsv$"
)


def log_identity(path: Path | str) -> dict[str, Any] | None:
    """``{"participant", "session", "study"}`` a response log's file name says (the inverse of
    :func:`session_paths`), or None for a name it does not make."""
    named = _TSV_NAME.match(Path(path).name)
    if named is None:
        return None
    return {
        "participant": named["participant"],
        "session": int(named["session"]),
        "study": named["study"],
    }


def session_paths(
    results: Path | str, *, study: str, participant: str, session: int
) -> SessionPaths:
    """Where one session's files live (see the module docstring)."""
    if not 1 <= session <= MAX_SESSION:
        raise StageError(f"session number {session}: expected 1..{MAX_SESSION}")
    folder = Path(results) / study / f"sub-{participant}" / f"ses-{session}"
    stem = f"sub-{participant}_ses-{session}_task-{study}"
    return SessionPaths(
        folder=folder,
        tsv=folder / f"{stem}_beh.tsv",
        dictionary=folder / f"{stem}_beh.json",
        provenance=folder / f"{stem}_session.json",
        repairs=folder / f"{stem}_repairs.tsv",
        playback=folder / f"{stem}_playback.jsonl",
        actions=folder / f"{stem}_actions.jsonl",
        staircase=folder / f"{stem}_staircase.jsonl",
        lock=folder / ".lock",
        screen_poses=folder / f"{stem}_screen_poses.jsonl",
    )


@dataclass(frozen=True)
class SessionContext:
    """What every row of one session repeats: who, which session, and its provenance."""

    study: str
    participant: str
    session: int
    simulated: bool
    protocol_sha256: str


# --------------------------------------------------------------------------- durability


@contextlib.contextmanager
def _signals_held() -> Iterator[None]:
    """Hold back SIGINT/SIGTERM/SIGHUP (delivered right after) while a line is written."""
    try:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, _HELD_SIGNALS)
    except (AttributeError, ValueError):  # not the main thread or no pthreads: write anyway
        yield
        return
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


def _append_line(path: Path, line: str) -> None:
    data = line.encode("utf-8")  # first: a line that cannot be written leaves the file as it was
    created = not path.exists()
    with _signals_held():
        with open(path, "ab") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        if created:
            fsync_dir(path.parent)


def append_jsonl(path: Path, record: Mapping[str, Any]) -> None:
    """Append one JSON object as a line to ``path`` and fsync it (playback, actions…)."""
    _append_line(path, json.dumps(dict(record), ensure_ascii=False) + "\n")


def _write_new(path: Path, text: str) -> None:
    data = text.encode("utf-8")  # first: text that cannot be written leaves no empty file
    with open(path, "xb") as fh:  # 'x': never overwrite
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())


# --------------------------------------------------------------------------- rows


def _format(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NA
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)  # round-trips exactly
    text = str(value)
    if any(ch in text for ch in "\t\n\r"):
        raise StageError(f"log value {text!r} contains a tab or newline")
    return text


_SHA256 = re.compile(r"[0-9a-f]{64}")


def _parse_row(values: list[str], columns: tuple[str, ...], *, where: str) -> dict[str, Any]:
    if len(values) != len(columns):
        raise StageError(
            f"{where}: expected {len(columns)} tab-separated fields, got {len(values)}"
        )
    row: dict[str, Any] = {}
    for name, text in zip(columns, values, strict=True):
        if text == NA:
            row[name] = None
        elif name in _INT_COLUMNS:
            try:
                row[name] = int(text)
            except ValueError:
                raise StageError(
                    f"{where}: column {name!r} should be an integer, got {text!r}"
                ) from None
        elif name in _FLOAT_COLUMNS:
            try:
                row[name] = float(text)
            except ValueError:
                raise StageError(
                    f"{where}: column {name!r} should be a number, got {text!r}"
                ) from None
        elif name in _BOOL_COLUMNS:
            if text not in ("true", "false"):
                raise StageError(f"{where}: column {name!r} should be true or false, got {text!r}")
            row[name] = text == "true"
        elif name == "timestamp":
            try:
                dt.datetime.fromisoformat(text)
            except ValueError:
                raise StageError(
                    f"{where}: column 'timestamp' should be a date and time (ISO 8601), got "
                    f"{text!r}"
                ) from None
            row[name] = text
        elif name == "protocol_sha256" and not _SHA256.fullmatch(text):
            # the last column: a line cut inside it reads as a cut line, not another protocol
            raise StageError(f"{where}: column 'protocol_sha256' should be 64 hex digits, got "
                             f"{text[:70]!r}")  # fmt: skip
        else:
            row[name] = text
    for name in LOG_COLUMNS:  # an old log: the newer columns are unknown
        row.setdefault(name, None)
    return row


def parse_log_text(text: str, *, source: str) -> tuple[list[dict[str, Any]], str | None]:
    """Parse a session TSV. Returns (rows, cut_tail) where cut_tail is a final line that
    has no newline and does not parse as a complete row (None if there is none).

    Every row has all of :data:`LOG_COLUMNS`; in an older log the newer ones are None.
    """
    _columns, rows, cut = _parse(text, source=source)
    return rows, cut


def _parse(text: str, *, source: str) -> tuple[tuple[str, ...], list[dict[str, Any]], str | None]:
    lines = text.split("\n")
    tail = lines.pop()  # text after the last newline ('' for a complete file)
    if not lines:
        if tail:
            return LOG_COLUMNS, [], tail  # even the header was cut off
        raise StageError(f"{source}: empty log file (no header)")
    header = tuple(lines[0].split("\t"))
    if header not in (LOG_COLUMNS, LOG_COLUMNS_V2, LOG_COLUMNS_V1):
        raise StageError(
            f"{source}:1: unexpected header; expected columns {', '.join(LOG_COLUMNS)}"
        )
    rows = [
        _parse_row(line.split("\t"), header, where=f"{source}:{number}")
        for number, line in enumerate(lines[1:], start=2)
    ]
    cut = None
    if tail:
        try:
            rows.append(_parse_row(tail.split("\t"), header, where=f"{source}:{len(lines) + 1}"))
        except StageError:
            cut = tail
    return header, rows, cut


def response_row(
    *,
    context: SessionContext,
    trial: Any,
    item: str,
    screen: str,
    rt_s: float,
    timestamp: str,
    clip_onset: float | None,
    clip_frames_dropped: int | None,
    rating: float | None = None,
    rating_start: float | None = None,
    response: str | None = None,
    correct: int | None = None,
    score: float | None = None,
    level: float | None = None,
) -> dict[str, Any]:
    """One log row for a response to ``trial`` (a :class:`facelab.design.Trial`)."""
    return {
        "study": context.study,
        "participant": context.participant,
        "session": context.session,
        "trial_index": trial.trial_index,
        "block": trial.block,
        "set_index": trial.set_index,
        "stimulus_set": trial.stimulus_set,
        "stimulus": trial.stimulus,
        "condition": trial.condition,
        "repetition": trial.repetition,
        "item": item,
        "rating": rating,
        "rating_start": rating_start,
        "rt_s": rt_s,
        "clip_onset": clip_onset,
        "clip_frames_dropped": clip_frames_dropped,
        "timestamp": timestamp,
        "screen": screen,
        "response": response,
        "correct": correct,
        "score": score,
        "level": level,
        "comparison": getattr(trial, "standard", None),
        "position": getattr(trial, "position", None),
        "simulated": context.simulated,
        "protocol_sha256": context.protocol_sha256,
    }


def utc_now() -> str:
    """The wall-clock time, ISO 8601 UTC with milliseconds (the ``timestamp`` column)."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="milliseconds")


# --------------------------------------------------------------------------- the lock


class SessionLock:
    """An exclusive lock on one session folder for as long as a process writes it.

    ``flock`` on ``<folder>/.lock``: a second process is refused at once with who holds it;
    the kernel drops the lock when the holder exits (also by SIGKILL or a crash), so a lock
    left behind never blocks ``--resume``.
    """

    def __init__(self, paths: SessionPaths):
        self.paths = paths
        self._fd: int | None = None

    def __enter__(self) -> SessionLock:
        import fcntl

        self.paths.folder.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.paths.lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            holder = os.pread(fd, 400, 0).decode("utf-8", errors="replace").strip()
            os.close(fd)
            raise SessionError(
                f"session {self.paths.folder} is in use by another process "
                f"({holder or 'unknown holder'}); a session has one writer - wait for it "
                "to end or stop it first (nothing was written)"
            ) from None
        info = f"pid {os.getpid()} on {socket.gethostname()} since {utc_now()}"
        os.ftruncate(fd, 0)
        os.pwrite(fd, info.encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc: object) -> None:
        if self._fd is not None:
            os.close(self._fd)  # releases the flock
            self._fd = None


# --------------------------------------------------------------------------- the log


@dataclass
class SessionLog:
    """An open, append-only session log. Create with :meth:`create` or :meth:`resume`."""

    paths: SessionPaths
    rows: list[dict[str, Any]] = field(default_factory=list)
    repaired: list[str] = field(default_factory=list)
    #: the columns of this file (a log begun before typed answers goes on without ``score``)
    columns: tuple[str, ...] = LOG_COLUMNS
    _keys: set[tuple[int, str]] = field(default_factory=set, init=False, repr=False)

    def __post_init__(self) -> None:
        self._keys = {(row["trial_index"], row["item"]) for row in self.rows}

    # -- opening

    @classmethod
    def create(
        cls,
        results: Path | str,
        *,
        study: str,
        participant: str,
        session: int,
        provenance: Mapping[str, Any],
    ) -> SessionLog:
        """Start a new session; refuses if the session folder already holds a log."""
        paths = session_paths(results, study=study, participant=participant, session=session)
        if paths.tsv.exists() or paths.provenance.exists():
            raise SessionError(
                f"session already exists: {paths.folder} (participant {participant}, session "
                f"{session}); nothing was overwritten. Use --resume to continue it, or choose "
                "another --session"
            )
        about = json.dumps(dict(provenance), indent=2, ensure_ascii=False) + "\n"
        about.encode("utf-8")  # text no file can hold fails here, before anything is written
        paths.folder.mkdir(parents=True, exist_ok=True)
        fsync_dir(paths.folder.parent)
        _write_new(paths.dictionary, json.dumps(COLUMN_DESCRIPTIONS, indent=2) + "\n")
        _write_new(paths.provenance, about)
        _write_new(paths.tsv, "\t".join(LOG_COLUMNS) + "\n")
        fsync_dir(paths.folder)
        return cls(paths=paths)

    @classmethod
    def resume(
        cls, results: Path | str, *, study: str, participant: str, session: int
    ) -> SessionLog:
        """Reopen an interrupted session, repairing a line cut off mid-write."""
        paths = session_paths(results, study=study, participant=participant, session=session)
        if not paths.tsv.exists():
            raise SessionError(f"nothing to resume: no log at {paths.tsv}")
        text = paths.tsv.read_bytes().decode("utf-8", errors="replace")
        header, rows, cut = _parse(text, source=str(paths.tsv))
        if header == LOG_COLUMNS_V1:
            raise SessionError(
                f"{paths.tsv} was written by facelab 0.1 (no provenance columns); finish that "
                "session with the facelab version that started it (it can still be analysed)"
            )
        log = cls(paths=paths, rows=rows, columns=header)
        if cut is not None or (text and not text.endswith("\n")):
            log._repair(text, cut)
        log._check_unique()
        return log

    def _repair(self, text: str, cut: str | None) -> None:
        keep = text[: text.rfind("\n") + 1] if cut is not None else text + "\n"
        if cut is not None:
            _append_line(self.paths.repairs, cut + "\n")
            self.repaired.append(cut)
        if not keep.strip():
            keep = "\t".join(self.columns) + "\n"
        replace_file(self.paths.tsv, keep)

    def _check_unique(self) -> None:
        seen = set()
        for row in self.rows:
            key = (row["trial_index"], row["item"])
            if key in seen:
                raise SessionError(
                    f"{self.paths.tsv}: trial {key[0]} item {key[1]!r} is logged twice"
                )
            seen.add(key)

    # -- writing

    def append(self, row: Mapping[str, Any]) -> None:
        """Write one response and force it to disk (write + fsync) before returning. A row
        without the columns added after :data:`LOG_COLUMNS_V2` has them missing (n/a)."""
        row = {**{c: None for c in LOG_COLUMNS if c not in LOG_COLUMNS_V2}, **row}
        missing = [c for c in LOG_COLUMNS if c not in row]
        extra = [c for c in row if c not in LOG_COLUMNS]
        if missing or extra:
            raise StageError(f"log row has missing {missing} / unknown {extra} columns")
        lost = [c for c in LOG_COLUMNS if c not in self.columns and row[c] is not None]
        if lost:
            raise SessionError(
                f"{self.paths.tsv} was begun by an earlier facelab without the column(s) "
                f"{', '.join(lost)} this answer needs; nothing was written - finish the session "
                "with that version, or start a new session"
            )
        line = "\t".join(_format(row[c]) for c in self.columns) + "\n"
        parsed = _parse_row(line[:-1].split("\t"), self.columns, where=str(self.paths.tsv))
        key = (parsed["trial_index"], parsed["item"])
        if key in self._keys:  # a set: appending stays O(1) however long the session
            raise SessionError(
                f"trial {key[0]} item {key[1]!r} is already logged; not writing it twice"
            )
        _append_line(self.paths.tsv, line)
        self.rows.append(parsed)
        self._keys.add(key)

    def answered(self) -> set[tuple[int, str]]:
        """(trial_index, item) of every response already logged."""
        return set(self._keys)

    def provenance(self) -> dict[str, Any]:
        """The session JSON as it is on disk."""
        return json.loads(self.paths.provenance.read_text(encoding="utf-8"))

    def update_provenance(self, **fields: Any) -> None:
        """Add keys to the session JSON (e.g. resume events), replacing it atomically."""
        data = self.provenance()
        for key, value in fields.items():
            if isinstance(data.get(key), list) and isinstance(value, list):
                data[key] = data[key] + value
            else:
                data[key] = value
        replace_file(self.paths.provenance, json.dumps(data, indent=2, ensure_ascii=False) + "\n")


def rows_to_tsv(rows: Iterable[Mapping[str, Any]]) -> str:
    """Rows as TSV text with the header (for exports and tests)."""
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter="\t", lineterminator="\n")
    writer.writerow(LOG_COLUMNS)
    for row in rows:
        writer.writerow([_format(row.get(c)) for c in LOG_COLUMNS])
    return buf.getvalue()
