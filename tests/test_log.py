"""Session logs: append + fsync per response, never overwrite, repair a line cut mid-write,
one writer, provenance on every row, old logs still readable."""

from __future__ import annotations

from pathlib import Path

import pytest

from facelab.errors import SessionError, StageError
from facelab.sessionlog import (
    LOG_COLUMNS,
    LOG_COLUMNS_V1,
    SessionLock,
    SessionLog,
    parse_log_text,
    rows_to_tsv,
    session_paths,
)


def _row(trial: int, item: str, rating: float = 50.0) -> dict[str, object]:
    return {
        "study": "s1",
        "participant": "P01",
        "session": 1,
        "trial_index": trial,
        "block": "b",
        "set_index": 1,
        "stimulus_set": "v",
        "stimulus": "x",
        "condition": "c",
        "repetition": 1,
        "item": item,
        "rating": rating,
        "rating_start": None,
        "rt_s": 1.25,
        "clip_onset": 3.5,
        "clip_frames_dropped": 0,
        "timestamp": "2026-01-01T00:00:00+00:00",
        "screen": "vas",
        "response": None,
        "correct": None,
        "level": None,
        "comparison": None,
        "position": None,
        "simulated": False,
        "protocol_sha256": "ab" * 32,
    }


def _create(tmp_path: Path) -> SessionLog:
    return SessionLog.create(
        tmp_path, study="s1", participant="P01", session=1, provenance={"seed": 1}
    )


def test_layout_and_each_row_is_on_disk_immediately(tmp_path: Path) -> None:
    log = _create(tmp_path)
    paths = session_paths(tmp_path, study="s1", participant="P01", session=1)
    assert log.paths == paths
    assert paths.tsv == tmp_path / "s1/sub-P01/ses-1/sub-P01_ses-1_task-s1_beh.tsv"
    assert paths.dictionary.exists() and paths.provenance.exists()
    log.append(_row(1, "a", 12.5))
    # read through a fresh file handle: the row is there before any close
    rows, cut = parse_log_text(paths.tsv.read_text(), source="t")
    assert cut is None and rows[0]["rating"] == 12.5 and rows[0]["rating_start"] is None
    assert paths.tsv.read_text().splitlines()[0].split("\t") == list(LOG_COLUMNS)


def test_existing_session_is_never_overwritten(tmp_path: Path) -> None:
    log = _create(tmp_path)
    log.append(_row(1, "a"))
    before = log.paths.tsv.read_bytes()
    with pytest.raises(StageError, match=r"session already exists.*--resume"):
        _create(tmp_path)
    assert log.paths.tsv.read_bytes() == before


def test_a_rating_cannot_be_logged_twice(tmp_path: Path) -> None:
    log = _create(tmp_path)
    log.append(_row(1, "a"))
    with pytest.raises(StageError, match="already logged"):
        log.append(_row(1, "a", 99.0))
    assert len(log.rows) == 1


def test_resume_moves_a_cut_off_line_to_the_repairs_file(tmp_path: Path) -> None:
    log = _create(tmp_path)
    log.append(_row(1, "a"))
    log.append(_row(1, "b"))
    with open(log.paths.tsv, "a", encoding="utf-8") as fh:  # power cut mid-write
        fh.write("s1\tP01\t1\t2\tb\t1\tv\tx\tc\t1\ta\t4")
    resumed = SessionLog.resume(tmp_path, study="s1", participant="P01", session=1)
    assert [(r["trial_index"], r["item"]) for r in resumed.rows] == [(1, "a"), (1, "b")]
    assert resumed.answered() == {(1, "a"), (1, "b")}
    assert resumed.repaired == ["s1\tP01\t1\t2\tb\t1\tv\tx\tc\t1\ta\t4"]
    assert resumed.paths.repairs.read_text().startswith("s1\tP01\t1\t2")
    assert resumed.paths.tsv.read_text().endswith("\n")
    resumed.append(_row(2, "a"))  # the cut rating is asked again and logged once
    again = SessionLog.resume(tmp_path, study="s1", participant="P01", session=1)
    assert [(r["trial_index"], r["item"]) for r in again.rows] == [(1, "a"), (1, "b"), (2, "a")]


def test_resume_keeps_a_complete_row_that_lost_only_its_newline(tmp_path: Path) -> None:
    log = _create(tmp_path)
    log.append(_row(1, "a"))
    text = log.paths.tsv.read_text()
    log.paths.tsv.write_text(text[:-1])  # newline lost
    resumed = SessionLog.resume(tmp_path, study="s1", participant="P01", session=1)
    assert len(resumed.rows) == 1 and not resumed.repaired
    assert resumed.paths.tsv.read_text() == text


def test_resume_without_a_session_and_corrupt_middle_lines(tmp_path: Path) -> None:
    with pytest.raises(StageError, match="nothing to resume"):
        SessionLog.resume(tmp_path, study="s1", participant="P09", session=1)
    log = _create(tmp_path)
    log.append(_row(1, "a"))
    with open(log.paths.tsv, "a", encoding="utf-8") as fh:
        fh.write("garbage line\n")
    with pytest.raises(StageError, match=r"_beh.tsv:3: expected 26 tab-separated fields"):
        SessionLog.resume(tmp_path, study="s1", participant="P01", session=1)


def test_update_provenance_appends_lists(tmp_path: Path) -> None:
    import json

    log = _create(tmp_path)
    log.update_provenance(resumes=["t1"])
    log.update_provenance(resumes=["t2"], note="x")
    data = json.loads(log.paths.provenance.read_text())
    assert data == {"seed": 1, "resumes": ["t1", "t2"], "note": "x"}


def test_provenance_columns_round_trip(tmp_path: Path) -> None:
    log = _create(tmp_path)
    log.append({**_row(1, "a"), "simulated": True})
    rows, _ = parse_log_text(log.paths.tsv.read_text(), source="t")
    assert rows[0]["simulated"] is True and rows[0]["protocol_sha256"] == "ab" * 32
    assert "\ttrue\t" in log.paths.tsv.read_text()


def test_a_facelab_01_log_is_read_but_not_continued(tmp_path: Path) -> None:
    paths = session_paths(tmp_path, study="s1", participant="P01", session=1)
    paths.folder.mkdir(parents=True)
    old = {k: v for k, v in _row(1, "a").items() if k in LOG_COLUMNS_V1}
    text = (
        "\t".join(LOG_COLUMNS_V1)
        + "\n"
        + "\t".join("n/a" if old[c] is None else str(old[c]) for c in LOG_COLUMNS_V1)
        + "\n"
    )
    paths.tsv.write_text(text)
    rows, cut = parse_log_text(text, source="old")
    assert cut is None and rows[0]["rating"] == 50.0 and rows[0]["simulated"] is None
    with pytest.raises(SessionError, match=r"written by facelab 0\.1"):
        SessionLog.resume(tmp_path, study="s1", participant="P01", session=1)


def test_one_writer_per_session_and_no_stale_lock(tmp_path: Path) -> None:
    import subprocess
    import sys

    paths = session_paths(tmp_path, study="s1", participant="P01", session=1)
    with (
        SessionLock(paths),
        pytest.raises(SessionError, match=r"in use by another process \(pid \d+"),
    ):
        SessionLock(paths).__enter__()
    # a holder that dies without releasing (SIGKILL) leaves no lock behind
    code = (
        "import os, sys; from pathlib import Path; from facelab.sessionlog import *; "
        f"SessionLock(session_paths(Path({str(tmp_path)!r}), study='s1', participant='P01', "
        "session=1)).__enter__(); os.kill(os.getpid(), 9)"
    )
    proc = subprocess.run([sys.executable, "-c", code], check=False)
    assert proc.returncode == -9
    with SessionLock(paths):
        pass


def test_session_numbers_are_bounded(tmp_path: Path) -> None:
    with pytest.raises(StageError, match=r"1\.\.9999"):
        session_paths(tmp_path, study="s1", participant="P01", session=10**20)


def test_rows_to_tsv_parses_back(tmp_path: Path) -> None:
    rows = [_row(1, "a", 1.5), _row(1, "b", 99.25)]
    parsed, cut = parse_log_text(rows_to_tsv(rows), source="x")
    assert cut is None and [r["rating"] for r in parsed] == [1.5, 99.25]


def test_log_identity_reads_back_what_session_paths_names(tmp_path) -> None:
    from facelab.sessionlog import log_identity, session_paths

    paths = session_paths(tmp_path, study="my_study-2", participant="P07", session=12)
    assert log_identity(paths.tsv) == {"participant": "P07", "session": 12, "study": "my_study-2"}
    assert log_identity(paths.playback) is None
    assert log_identity(tmp_path / "notes.tsv") is None


def test_text_no_file_can_hold_leaves_no_half_written_file(tmp_path: Path) -> None:
    """A lone surrogate in a session's provenance or a JSON line fails before the file is
    opened: no empty _session.json (an export once left one), the JSON lines file as it was."""
    from facelab.sessionlog import append_jsonl

    with pytest.raises(UnicodeEncodeError):
        SessionLog.create(tmp_path, study="s", participant="P01", session=1,
                          provenance={"browser": {"ua": "\ud800"}})  # fmt: skip
    paths = session_paths(tmp_path, study="s", participant="P01", session=1)
    assert not paths.folder.exists()  # nothing written: a second try starts clean
    lines = tmp_path / "x.jsonl"
    append_jsonl(lines, {"a": 1})
    with pytest.raises(UnicodeEncodeError):
        append_jsonl(lines, {"a": "\udfff"})
    assert lines.read_text(encoding="utf-8") == '{"a": 1}\n'
