"""Edits of written session logs for tests of the analysis on data an experimenter could
have (every rating of an item alike, a perfect effect, a participant's second session): the
log's rows rewritten in place, tab-separated as the runner writes them."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path


def rewrite_rows(root: Path, change: Callable[[dict[str, str]], bool]) -> int:
    """Apply ``change`` (edits the row in place, returns whether it did) to every row of the
    ``*_beh.tsv`` logs at or under ``root``; returns how many rows changed."""
    changed = 0
    for tsv in [root] if root.is_file() else sorted(root.rglob("*_beh.tsv")):
        lines = tsv.read_text(encoding="utf-8").split("\n")
        header = lines[0].split("\t")
        out = [lines[0]]
        for line in lines[1:]:
            if line:
                row = dict(zip(header, line.split("\t"), strict=True))
                changed += bool(change(row))
                line = "\t".join(row[k] for k in header)
            out.append(line)
        tsv.write_text("\n".join(out), encoding="utf-8")
    return changed


def rewrite_ratings(
    root: Path, *, item: str, stimulus_set: str, rating: Callable[[dict[str, str]], float]
) -> int:
    """Set ``rating`` (a function of the row) on every VAS row of ``item`` / ``stimulus_set``
    in the logs under ``root``; returns how many rows changed."""

    def change(row: dict[str, str]) -> bool:
        if row["item"] != item or row["stimulus_set"] != stimulus_set:
            return False
        row["rating"] = f"{rating(row):g}"
        return True

    return rewrite_rows(root, change)
