"""File formats that cross layers, each with its one reader (and writer where shared):

* the clip manifest ``clips.csv`` (DESIGN.md: :data:`CLIP_COLUMNS`) written by the stimulus
  layer, read by sessions, the online server and the analysis (:func:`read_manifest`,
  :func:`write_manifest`);
* the behaviour event log ``<clip_id>.behaviour.json`` beside a clip (:func:`read_behaviour_log`);
* the impression model file's header (:data:`IMPRESSION_FORMAT`,
  :func:`impression_header_problems`), checked by the protocol loader without reading the model.

``write_manifest`` writes atomically and, for the tools that render part of a set at a time
(``facelab impression render`` one expression, ``facelab behaviour render`` some emotions),
keeps the rows of clips rendered earlier into the same folder. A kept row must name a clip
that is not rendered now, whose file is still in the folder, and come from a manifest with the
same columns; anything else is dropped and named, so the manifest never lists a file that is
gone and never forgets one that is there.
"""

from __future__ import annotations

import csv
import json
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

from facelab.errors import FormatError, StageError

__all__ = [
    "BEHAVIOUR_LOG_SUFFIX",
    "CLIP_COLUMNS",
    "IMPRESSION_FORMAT",
    "MANIFEST_NAME",
    "behaviour_log_path",
    "impression_header_problems",
    "read_behaviour_log",
    "read_manifest",
    "write_manifest",
]

#: the clip manifest's file name and columns (DESIGN.md); a protocol's clips have them all
MANIFEST_NAME = "clips.csv"
CLIP_COLUMNS = (
    "clip_id",
    "stimulus_set",
    "stimulus",
    "condition",
    "path",
    "duration_s",
    "fps",
    "width",
    "height",
    "sha256",
    "spec_sha256",
)
#: the suffix of a clip's behaviour event log, beside the clip
BEHAVIOUR_LOG_SUFFIX = ".behaviour.json"
#: the format id in an impression model file (``facelab impression fit``)
IMPRESSION_FORMAT = "facelab-impression-1"


def read_manifest(clips_dir: Path, *, need: Sequence[str] = ()) -> list[dict[str, str]]:
    """The rows of ``clips_dir/clips.csv`` (strings), each with at least the columns
    ``need``. Raises :class:`FormatError` naming the file when it is missing, unreadable or
    lacks a needed column."""
    path = Path(clips_dir) / MANIFEST_NAME
    if not path.is_file():
        raise FormatError(f"no clip manifest at {path}: render the clips first")
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = list(reader.fieldnames or [])
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error):
        raise FormatError(f"{path}: not a readable CSV clip manifest") from None
    lacking = [c for c in need if c not in header]
    if lacking:
        raise FormatError(
            f"{path}: no column {', '.join(lacking)} (written by an older facelab?); "
            "render the clips again"
        )
    return rows


def behaviour_log_path(clips_dir: Path, clip_id: str) -> Path:
    """Where the behaviour event log of clip ``clip_id`` lives."""
    return Path(clips_dir) / f"{clip_id}{BEHAVIOUR_LOG_SUFFIX}"


def read_behaviour_log(path: Path) -> dict[str, Any]:
    """A behaviour event log: ``{"mode", "events": [{"unit", "layer", "start_s", "end_s",
    …}], "realisation": {…}}``. Raises :class:`FormatError` naming the file."""
    try:
        log = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        raise FormatError(f"{path}: not a readable JSON behaviour log") from None
    events = log.get("events") if isinstance(log, dict) else None
    if not isinstance(events, list) or not all(
        isinstance(e, dict) and {"unit", "layer"} <= set(e) for e in events
    ):
        raise FormatError(f"{path}: a behaviour log has a list 'events' of units with layers")
    return log


def impression_header_problems(
    path: Path, *, expression: str | None = None, space: str | None = None
) -> Iterator[tuple[str, str]]:
    """What is wrong with an impression model file for a use: ``(key, message)`` pairs, the
    key ``model`` or ``expression``. Reads only the header (format, space, expressions)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        yield "model", f"{path} was not found"
        return
    except (OSError, UnicodeDecodeError, ValueError):
        yield "model", f"{path}: not a readable JSON file"
        return
    if not isinstance(data, dict) or data.get("format") != IMPRESSION_FORMAT:
        yield "model", f"{path}: not a facelab impression model ({IMPRESSION_FORMAT})"
        return
    if space is not None and data.get("space") != space:
        yield (
            "model",
            f"{path}: a {data.get('space')}-space model; conditions need an ARKit-space model "
            "(render vertex-space models with facelab impression render)",
        )
    expressions = sorted(data.get("directions") or {})
    if expression is not None and expression not in expressions:
        yield (
            "expression",
            f"the model has no expression {expression!r}; it has {', '.join(expressions)}",
        )


def _earlier_rows(path: Path, columns: Sequence[str]) -> tuple[list[dict], list[str]]:
    """Rows of an existing manifest, and notes on what cannot be kept."""
    if not path.is_file():
        return [], []
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = list(reader.fieldnames or [])
            rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as exc:
        aside = path.with_name("clips.csv.unreadable")
        path.replace(aside)
        return [], [f"{path}: cannot read the manifest there ({exc}); moved it to {aside.name}"]
    except OSError as exc:
        raise StageError(f"{path}: cannot read the existing manifest ({exc})") from exc
    if header != list(columns):
        return [], [
            f"{path.name} had other columns ({', '.join(header[:4])}, ...): "
            "its rows are replaced, not merged"
        ]
    return rows, []


def write_manifest(
    out: Path,
    rows: list[dict],
    *,
    columns: Sequence[str],
    merge: bool = False,
    provenance: str | None = None,
) -> list[str]:
    """Write ``out/clips.csv`` with ``rows`` (each a dict over ``columns``).

    With ``merge``, rows of the manifest already there are kept (before the new rows, in
    their order) when their clip is not among ``rows`` and their ``path`` still exists in
    ``out``. ``provenance`` names a column (e.g. the model's hash): kept rows whose value
    differs from the new rows' get a note. Returns notes for the user: what was kept, what
    was dropped and why.
    """
    path = out / MANIFEST_NAME
    notes: list[str] = []
    kept: list[dict] = []
    if merge:
        earlier, notes = _earlier_rows(path, columns)
        new_ids = {str(r["clip_id"]) for r in rows}
        gone = []
        for row in earlier:
            if row.get("clip_id") in new_ids:
                continue
            if not (out / str(row.get("path", ""))).is_file():
                gone.append(str(row.get("clip_id")))
                continue
            kept.append(row)
        if kept:
            notes.append(f"kept {len(kept)} clip(s) rendered earlier into {out} in clips.csv")
        if provenance and rows:
            now = {str(r[provenance]) for r in rows}
            other = [str(r["clip_id"]) for r in kept if r.get(provenance) not in now]
            if other:
                notes.append(
                    f"{len(other)} kept clip(s) have another {provenance} than these "
                    f"({', '.join(other[:5])}{', ...' if len(other) > 5 else ''}): "
                    "render into a new folder to keep them apart"
                )
        if gone:
            notes.append(
                f"dropped {len(gone)} earlier row(s) whose file is gone: {', '.join(gone)}"
            )
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(
            fh, fieldnames=list(columns), lineterminator="\n", extrasaction="ignore"
        )
        writer.writeheader()
        writer.writerows(kept)
        writer.writerows(rows)
    tmp.replace(path)
    return notes
