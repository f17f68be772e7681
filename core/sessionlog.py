"""Session logs: one row per rating, appended and fsync'd the moment it is given.

Layout (BIDS-style, one folder per participant session)::

    results/<study>/sub-<ID>/ses-<N>/
        sub-<ID>_ses-<N>_task-<study>_beh.tsv      the ratings (this module appends to it)
        sub-<ID>_ses-<N>_task-<study>_beh.json     data dictionary of the TSV columns
        sub-<ID>_ses-<N>_task-<study>_session.json provenance: protocol hash, seed, trial
                                                   order, clip hashes, software, screen/audio
        sub-<ID>_ses-<N>_task-<study>_playback.jsonl  every flip of every clip (the runner)
        sub-<ID>_ses-<N>_task-<study>_repairs.tsv  only after a crash: cut-off lines kept verbatim

Rules: a session folder that exists is never overwritten (:meth:`SessionLog.create` refuses);
:meth:`SessionLog.resume` reopens it. A last line cut off mid-write (no newline, e.g. power
loss) is detected on resume: if it still parses as a complete row it is kept, otherwise it is
moved verbatim to the repairs file and that rating is asked again - never silently dropped
or duplicated. Missing values are written ``n/a``, as BIDS does.
"""

from __future__ import annotations

import csv
import io
import json
import math
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from facelab.errors import StageError

__all__ = [
    "COLUMN_DESCRIPTIONS",
    "LOG_COLUMNS",
    "SessionLog",
    "SessionPaths",
    "parse_log_text",
    "rating_row",
    "session_paths",
]

LOG_COLUMNS: tuple[str, ...] = (
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

COLUMN_DESCRIPTIONS: dict[str, dict[str, str]] = {
    "study": {"Description": "Study id from the protocol."},
    "participant": {"Description": "Participant id (letters and digits)."},
    "session": {"Description": "Session number, from 1."},
    "trial_index": {"Description": "Position of the trial in the session's design, from 1."},
    "block": {"Description": "Block id from the protocol."},
    "set_index": {"Description": "Set number within the block, from 1."},
    "stimulus_set": {"Description": "Stimulus set id."},
    "stimulus": {"Description": "Stimulus id within the set."},
    "condition": {"Description": "Animation condition id."},
    "repetition": {"Description": "Nth showing of this stimulus and condition within the set."},
    "item": {"Description": "VAS item id."},
    "rating": {
        "Description": "The confirmed VAS position.",
        "Units": "scale points (0 = left anchor)",
    },
    "rating_start": {
        "Description": "Marker position shown before the first click; n/a when the "
        "marker is hidden until the first click."
    },
    "rt_s": {"Description": "Time from the item appearing to the confirmation.", "Units": "s"},
    "clip_onset": {
        "Description": "Flip time of the clip's first frame on the session clock.",
        "Units": "s",
    },
    "clip_frames_dropped": {"Description": "Frames of the clip shown late (dropped)."},
    "timestamp": {"Description": "Wall-clock time the rating was confirmed (ISO 8601, UTC)."},
}

_INT_COLUMNS = {"session", "trial_index", "set_index", "repetition", "clip_frames_dropped"}
_FLOAT_COLUMNS = {"rating", "rating_start", "rt_s", "clip_onset"}
NA = "n/a"


@dataclass(frozen=True)
class SessionPaths:
    folder: Path
    tsv: Path
    dictionary: Path
    provenance: Path
    repairs: Path


def session_paths(
    results: Path | str, *, study: str, participant: str, session: int
) -> SessionPaths:
    """Where one session's files live (see the module docstring)."""
    folder = Path(results) / study / f"sub-{participant}" / f"ses-{session}"
    stem = f"sub-{participant}_ses-{session}_task-{study}"
    return SessionPaths(
        folder=folder,
        tsv=folder / f"{stem}_beh.tsv",
        dictionary=folder / f"{stem}_beh.json",
        provenance=folder / f"{stem}_session.json",
        repairs=folder / f"{stem}_repairs.tsv",
    )


def _format(value: Any) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return NA
    if isinstance(value, float):
        return repr(value)  # round-trips exactly
    text = str(value)
    if any(ch in text for ch in "\t\n\r"):
        raise StageError(f"log value {text!r} contains a tab or newline")
    return text


def _parse_row(values: list[str], *, where: str) -> dict[str, Any]:
    if len(values) != len(LOG_COLUMNS):
        raise StageError(
            f"{where}: expected {len(LOG_COLUMNS)} tab-separated fields, got {len(values)}"
        )
    row: dict[str, Any] = {}
    for name, text in zip(LOG_COLUMNS, values, strict=True):
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
        else:
            row[name] = text
    return row


def parse_log_text(text: str, *, source: str) -> tuple[list[dict[str, Any]], str | None]:
    """Parse a session TSV. Returns (rows, cut_tail) where cut_tail is a final line that
    has no newline and does not parse as a complete row (None if there is none)."""
    lines = text.split("\n")
    tail = lines.pop()  # text after the last newline ('' for a complete file)
    if not lines:
        if tail:
            return [], tail  # even the header was cut off
        raise StageError(f"{source}: empty log file (no header)")
    header = lines[0].split("\t")
    if tuple(header) != LOG_COLUMNS:
        raise StageError(
            f"{source}:1: unexpected header; expected columns {', '.join(LOG_COLUMNS)}"
        )
    rows = [
        _parse_row(line.split("\t"), where=f"{source}:{number}")
        for number, line in enumerate(lines[1:], start=2)
    ]
    cut = None
    if tail:
        try:
            rows.append(_parse_row(tail.split("\t"), where=f"{source}:{len(lines) + 1}"))
        except StageError:
            cut = tail
    return rows, cut


@dataclass
class SessionLog:
    """An open, append-only session log. Create with :meth:`create` or :meth:`resume`."""

    paths: SessionPaths
    rows: list[dict[str, Any]] = field(default_factory=list)
    repaired: list[str] = field(default_factory=list)

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
            raise StageError(
                f"session already exists: {paths.folder} (participant {participant}, session "
                f"{session}); nothing was overwritten. Use --resume to continue it, or choose "
                "another --session"
            )
        paths.folder.mkdir(parents=True, exist_ok=True)
        _write_new(paths.dictionary, json.dumps(COLUMN_DESCRIPTIONS, indent=2) + "\n")
        _write_new(
            paths.provenance, json.dumps(dict(provenance), indent=2, ensure_ascii=False) + "\n"
        )
        _write_new(paths.tsv, "\t".join(LOG_COLUMNS) + "\n")
        return cls(paths=paths)

    @classmethod
    def resume(
        cls, results: Path | str, *, study: str, participant: str, session: int
    ) -> SessionLog:
        """Reopen an interrupted session, repairing a line cut off mid-write."""
        paths = session_paths(results, study=study, participant=participant, session=session)
        if not paths.tsv.exists():
            raise StageError(f"nothing to resume: no log at {paths.tsv}")
        text = paths.tsv.read_bytes().decode("utf-8", errors="replace")
        rows, cut = parse_log_text(text, source=str(paths.tsv))
        log = cls(paths=paths, rows=rows)
        if cut is not None or (text and not text.endswith("\n")):
            log._repair(text, cut)
        log._check_unique()
        return log

    def _repair(self, text: str, cut: str | None) -> None:
        keep = text[: text.rfind("\n") + 1] if cut is not None else text + "\n"
        if cut is not None:
            with open(self.paths.repairs, "a", encoding="utf-8") as fh:
                fh.write(cut + "\n")
                fh.flush()
                os.fsync(fh.fileno())
            self.repaired.append(cut)
        if not keep.strip():
            keep = "\t".join(LOG_COLUMNS) + "\n"
        with open(self.paths.tsv, "r+b") as fh:
            fh.seek(0)
            fh.write(keep.encode("utf-8"))
            fh.truncate()
            fh.flush()
            os.fsync(fh.fileno())

    def _check_unique(self) -> None:
        seen = set()
        for row in self.rows:
            key = (row["trial_index"], row["item"])
            if key in seen:
                raise StageError(
                    f"{self.paths.tsv}: trial {key[0]} item {key[1]!r} is logged twice"
                )
            seen.add(key)

    # -- writing

    def append(self, row: Mapping[str, Any]) -> None:
        """Write one rating and force it to disk (flush + fsync) before returning."""
        missing = [c for c in LOG_COLUMNS if c not in row]
        extra = [c for c in row if c not in LOG_COLUMNS]
        if missing or extra:
            raise StageError(f"log row has missing {missing} / unknown {extra} columns")
        key = (row["trial_index"], row["item"])
        if any((r["trial_index"], r["item"]) == key for r in self.rows):
            raise StageError(
                f"trial {key[0]} item {key[1]!r} is already logged; not writing it twice"
            )
        line = "\t".join(_format(row[c]) for c in LOG_COLUMNS) + "\n"
        with open(self.paths.tsv, "a", encoding="utf-8", newline="") as fh:
            fh.write(line)
            fh.flush()
            os.fsync(fh.fileno())
        self.rows.append(_parse_row(line[:-1].split("\t"), where=str(self.paths.tsv)))

    def answered(self) -> dict[int, set[str]]:
        """Items already rated, by trial index."""
        out: dict[int, set[str]] = {}
        for row in self.rows:
            out.setdefault(row["trial_index"], set()).add(row["item"])
        return out

    def update_provenance(self, **fields: Any) -> None:
        """Add keys to the session JSON (e.g. resume events), replacing it atomically."""
        data = json.loads(self.paths.provenance.read_text(encoding="utf-8"))
        for key, value in fields.items():
            if isinstance(data.get(key), list) and isinstance(value, list):
                data[key] = data[key] + value
            else:
                data[key] = value
        tmp = self.paths.provenance.with_suffix(".json.tmp")
        tmp.write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")
        with open(tmp, "rb") as fh:
            os.fsync(fh.fileno())
        os.replace(tmp, self.paths.provenance)


def rating_row(
    *,
    study: str,
    participant: str,
    session: int,
    trial: Any,
    item: str,
    rating: float,
    rt_s: float,
    clip_onset: float,
    clip_frames_dropped: int,
    timestamp: str,
    rating_start: float | None = None,
) -> dict[str, Any]:
    """One log row for a rating of ``trial`` (an ``facelab.design.Trial``)."""
    return {
        "study": study,
        "participant": participant,
        "session": session,
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
    }


def _write_new(path: Path, text: str) -> None:
    with open(path, "x", encoding="utf-8") as fh:  # 'x': never overwrite
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())


def rows_to_tsv(rows: Iterable[Mapping[str, Any]]) -> str:
    """Rows as TSV text with the header (for exports and tests)."""
    buf = io.StringIO()
    writer = csv.writer(buf, delimiter="\t", lineterminator="\n")
    writer.writerow(LOG_COLUMNS)
    for row in rows:
        writer.writerow([_format(row[c]) for c in LOG_COLUMNS])
    return buf.getvalue()
