"""Writing a folder's ``clips.csv``: atomically, and for the tools that render part of a set
at a time (``facelab impression render`` one expression, ``facelab behaviour render`` some
emotions), keeping the rows of clips rendered earlier into the same folder.

A kept row must name a clip that is not rendered now, whose file is still in the folder, and
come from a manifest with the same columns; anything else is dropped and named, so the
manifest never lists a file that is gone and never forgets one that is there.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path

from facelab.errors import StageError

__all__ = ["write_manifest"]


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
    path = out / "clips.csv"
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
