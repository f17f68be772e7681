"""Session logs from a results folder -> one validated long DataFrame (one row per rating).

``load_results`` finds every ``sub-*/ses-*/*_beh.tsv`` under the folder, parses each with
the same reader the runner uses for resuming, and checks the whole: the DESIGN.md columns,
one study only, no rating given twice, ratings inside the scale, no missing ratings.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pandas as pd

from facelab.errors import AnalysisError, StageError
from facelab.sessionlog import LOG_COLUMNS, log_identity, parse_log_text, session_paths
from facelab.textfiles import read_text

__all__ = ["find_logs", "frame_from_rows", "load_log", "load_results", "session_summary"]


def find_logs(results: Path | str) -> list[Path]:
    """All session TSVs below ``results`` (a results root or one study's folder), sorted."""
    root = Path(results)
    if root.is_file():
        raise AnalysisError(f"{root} is a file; expected the results folder (results/ or one "
                            "study's folder)")  # fmt: skip
    if not root.is_dir():
        raise AnalysisError(f"results folder not found: {root}")
    return sorted(root.rglob("sub-*/ses-*/sub-*_beh.tsv"))


def _read_rows(path: Path) -> list[dict]:
    """One session TSV's rows (dicts with :data:`LOG_COLUMNS` and ``source``), provenance
    filled from the session file for logs older than the provenance columns."""
    text = read_text(path, error=AnalysisError, encoding="utf-8")
    try:
        rows, cut = parse_log_text(text, source=str(path))
    except StageError as exc:
        raise AnalysisError(str(exc)) from None
    if cut is not None:
        raise AnalysisError(
            f"{path}: the last line was cut off mid-write ({cut[:40]!r}…); run the session "
            "with --resume to repair it, then analyse"
        )
    source = str(path)
    _check_identity(rows, path)
    for row in rows:
        row["source"] = source
    # the session file beside the log must read (an export cut short leaves it empty)
    sidecar = path.with_name(path.name.replace("_beh.tsv", "_session.json"))
    meta = _session_file(sidecar, identity=log_identity(path)) if sidecar.exists() else None
    # provenance: on every row since facelab 0.2; older logs take it from the session file
    if meta is not None and any(
        r["simulated"] is None or r["protocol_sha256"] is None for r in rows
    ):
        for row in rows:
            if row["simulated"] is None and "simulated" in meta:
                row["simulated"] = bool(meta["simulated"])
            if row["protocol_sha256"] is None and meta.get("protocol_sha256"):
                row["protocol_sha256"] = meta["protocol_sha256"]
    return rows


def _session_file(path: Path, *, identity: dict | None = None) -> dict:
    """A session's provenance file, refused in words when it is empty or does not read, or
    when its participant, session or ``simulated`` flag is not what the log's name says or
    not of its type (``identity``: what the name says, :func:`log_identity`)."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        raise AnalysisError(f"{path}: the session file cannot be read as UTF-8 text; "
                            "export or copy the session again") from None  # fmt: skip
    if not text.strip():
        raise AnalysisError(f"{path}: the session file is empty (an export or copy cut "
                            "short?); export the session again before analysing")  # fmt: skip
    try:
        meta = json.loads(text)
    except json.JSONDecodeError as exc:
        raise AnalysisError(f"{path}: not valid JSON (line {exc.lineno}: {exc.msg})") from None
    if not isinstance(meta, dict):
        raise AnalysisError(f"{path}: expected a JSON object (the session's provenance)")
    session = meta.get("session", 1)
    if isinstance(session, bool) or not isinstance(session, int) or session < 1:
        raise AnalysisError(f"{path}: \"session\" is {session!r}, expected a whole number >= 1; "
                            "was the file edited?")  # fmt: skip
    if "simulated" in meta and not isinstance(meta["simulated"], bool):
        raise AnalysisError(f"{path}: \"simulated\" is {meta['simulated']!r}, expected true or "
                            "false; was the file edited?")  # fmt: skip
    for key, value in (identity or {}).items():
        if key in meta and meta[key] != value:
            raise AnalysisError(
                f"{path}: {key} is {meta[key]!r}, but the log's name says {value!r}; was the "
                "file edited or copied from another session?"
            )
    return meta


def sessions_without_responses(results: Path | str, *, study: str) -> list[str]:
    """``"P01/1 (why)"`` for every session folder of ``study`` below ``results`` that holds
    no response: no response log (a session stopped before its first answer, or a log lost
    in a copy) or one with only its header line. Such sessions are in no table; the report
    names them."""
    out = []
    for folder in sorted(Path(results).rglob("sub-*/ses-*")):
        participant = folder.parent.name.removeprefix("sub-")
        session = folder.name.removeprefix("ses-")
        if not folder.is_dir() or not session.isdigit():
            continue
        try:  # the names of this study's session files (not those of a study named alike)
            paths = session_paths(".", study=study, participant=participant, session=int(session))
        except StageError:
            continue
        names = {getattr(paths, f.name).name for f in dataclasses.fields(paths)
                 if f.name != "folder"}  # fmt: skip
        mine = sorted(p for p in folder.iterdir() if p.name in names and p.is_file())
        logs = [p for p in mine if p.name == paths.tsv.name]
        if not mine:
            continue
        name = f"{participant}/{session}"
        if not logs:
            out.append(f"{name} (no response log beside its {mine[0].name})")
            continue
        try:
            lines = logs[0].read_text(encoding="utf-8").splitlines()
        except (OSError, UnicodeDecodeError):
            continue  # load_results names it
        if sum(1 for line in lines if line.strip()) <= 1:
            out.append(f"{name} (its response log holds only the header line)")
    return out


#: what names a response: every row has these (the others may be n/a)
IDENTITY_COLUMNS = (
    "study",
    "participant",
    "session",
    "trial_index",
    "block",
    "stimulus_set",
    "stimulus",
    "condition",
    "item",
)


def _check_identity(rows: list[dict], path: Path) -> None:
    """Every row names its response, and the participant, session and study the file's name
    says (sub-<ID>_ses-<N>_task-<study>_beh.tsv): a row edited by hand or pasted from another
    participant's log is an error, not a response analysed under the wrong name."""
    expected = log_identity(path) or {}
    for line, row in enumerate(rows, start=2):
        for column in IDENTITY_COLUMNS:
            if row.get(column) is None:
                raise AnalysisError(f"{path}:{line}: column {column!r} is empty (n/a)")
        for column, value in expected.items():
            if row[column] != value:
                raise AnalysisError(
                    f"{path}:{line}: {column} is {row[column]!r}, but the file's name says "
                    f"{value!r}; was the log edited or copied from another session?"
                )


def frame_from_rows(rows: list[dict]) -> pd.DataFrame:
    """Log rows (dicts with :data:`LOG_COLUMNS`) as the DataFrame the analyses take."""
    frame = pd.DataFrame(rows, columns=[*LOG_COLUMNS, "source"])
    frame["simulated"] = frame["simulated"].astype(object)
    return frame


def load_log(path: Path | str) -> pd.DataFrame:
    """One session TSV as a DataFrame with :data:`LOG_COLUMNS` (and ``source``).

    A last line cut off mid-write is an error here (resume the session to repair it).
    """
    return frame_from_rows(_read_rows(Path(path)))


def load_results(
    results: Path | str, *, study: str | None = None, scale: tuple[float, float] = (0.0, 100.0)
) -> pd.DataFrame:
    """Every session below ``results`` as one long DataFrame, validated.

    Parameters
    ----------
    results : a results root (``results/``) or one study's folder.
    study : keep only this study; without it, more than one study is an error.
    scale : the VAS range every rating must lie in.
    """
    logs = find_logs(results)
    if not logs:
        raise AnalysisError(f"no session logs (sub-*/ses-*/*_beh.tsv) under {results}")
    frame = frame_from_rows([row for p in logs for row in _read_rows(p)])
    studies = sorted(frame["study"].dropna().unique())
    if study is not None:
        frame = frame[frame["study"] == study].reset_index(drop=True)
        if frame.empty:
            raise AnalysisError(f"no ratings for study {study!r} under {results}; found {studies}")
    elif len(studies) > 1:
        raise AnalysisError(
            f"ratings from more than one study under {results}: {', '.join(studies)}; "
            "pass the study's own folder"
        )
    missing = frame["rating"].isna() & (frame["screen"].fillna("vas") == "vas")
    if missing.any():
        first = frame[missing].iloc[0]
        raise AnalysisError(
            f"{first['source']}: trial {first['trial_index']} item {first['item']!r} has no rating"
        )
    low, high = scale
    outside = (frame["rating"] < low) | (frame["rating"] > high)
    if outside.any():
        first = frame[outside].iloc[0]
        raise AnalysisError(
            f"{first['source']}: rating {first['rating']:g} (trial {first['trial_index']}, item "
            f"{first['item']!r}) is outside the scale {low:g}..{high:g}"
        )
    key = ["participant", "session", "trial_index", "item"]
    dup = frame.duplicated(key, keep=False)
    if dup.any():
        first = frame[dup].iloc[0]
        raise AnalysisError(
            f"rating given twice: participant {first['participant']} session {first['session']} "
            f"trial {first['trial_index']} item {first['item']!r} ({first['source']})"
        )
    return frame


def session_summary(frame: pd.DataFrame) -> pd.DataFrame:
    """Ratings per participant session, with whether it was simulated."""
    return frame.groupby(["participant", "session"], as_index=False).agg(
        responses=("item", "size"),
        trials=("trial_index", "nunique"),
        simulated=("simulated", lambda s: "unknown" if s.isna().any() else bool(s.all())),
        first=("timestamp", "min"),
        last=("timestamp", "max"),
    )
