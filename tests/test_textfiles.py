"""Users' CSV tables (``facelab.textfiles.read_rows``): every way a table is malformed is
refused with the file and line, never read as shifted or truncated rows."""

from __future__ import annotations

from pathlib import Path

import pytest

from facelab.errors import StageError
from facelab.textfiles import read_json, read_rows


def _table(tmp_path: Path, data: bytes | str) -> Path:
    path = tmp_path / "t.csv"
    path.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)
    return path


def test_rows_come_with_their_header_and_lines(tmp_path: Path) -> None:
    rows = read_rows(_table(tmp_path, "\ufeffa,b\n\n1,\"x,y\"\n2,z\n"), required=("a", "b"))
    assert rows == [{"a": "1", "b": "x,y"}, {"a": "2", "b": "z"}]
    assert rows.header == ["a", "b"] and rows.lines == [3, 4]  # the BOM dropped, a blank skipped
    # a separator at the end of every line, or of the data lines only, names no column
    assert read_rows(_table(tmp_path, "a,b,\n1,2,\n")) == [{"a": "1", "b": "2"}]
    assert read_rows(_table(tmp_path, "a,b\n1,2,\n3,4\n")) == [{"a": "1", "b": "2"},
                                                                {"a": "3", "b": "4"}]  # fmt: skip
    # tab- or semicolon-separated when asked to tell them apart
    assert read_rows(_table(tmp_path, "a\tb\n1\t2\n"), delimiter=None) == [{"a": "1", "b": "2"}]
    assert read_rows(_table(tmp_path, "a;b\n1;2,5\n"), delimiter=None) == [{"a": "1", "b": "2,5"}]
    # spreadsheets' used range: empty columns named by nothing at the header's end
    assert read_rows(_table(tmp_path, "a,b,,\n1,2,,\n")) == [{"a": "1", "b": "2"}]
    # a quoted value keeps its line break (keywords one per line) and the next row its line;
    # a line separator that is not \n or \r is part of the value
    rows = read_rows(_table(tmp_path, 'a,b\n1,"x\ny"\n2,z\u2028w\n'))
    assert rows == [{"a": "1", "b": "x\ny"}, {"a": "2", "b": "z\u2028w"}] and rows.lines == [2, 4]
    header_only = read_rows(_table(tmp_path, "a,b\n"))
    assert header_only == [] and header_only.header == ["a", "b"]


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ("", r"t\.csv: empty; expected a header line with a, b"),
        (" , \n,,\n", r"t\.csv: empty; expected a header line with a, b"),
        ("a,b\n1,2,3\n", r"t\.csv:2: 3 fields, the header has 2 \(put a value that contains a"),
        ("a,b\n1\n", r"t\.csv:2: 1 fields, the header has 2"),
        ("a,b\n1,\"2\n3,4\n5,6\n", r"t\.csv:2: a value's double quotes are not closed"),
        ("a,a\n1,2\n", r"t\.csv:1: column\(s\) named twice in the header: a"),
        ("a,,b\n1,2,3\n", r"t\.csv:1: a column has no name"),
        ("x,y\n1,2\n", r"t\.csv:1: missing column\(s\) a, b; expected a, b in the header line"),
        (b"a,b\n1,\xe9\n", r"t\.csv:2: not UTF-8 text \(byte 0xe9\); save it as UTF-8"),
    ],
)
def test_a_malformed_table_is_refused_at_its_line(
    tmp_path: Path, data: str | bytes, message: str
) -> None:
    with pytest.raises(StageError, match=message):
        read_rows(_table(tmp_path, data), required=("a", "b"))


def test_a_folder_or_a_missing_file_is_named(tmp_path: Path) -> None:
    with pytest.raises(StageError, match=r"is a folder, expected a file"):
        read_rows(tmp_path)
    with pytest.raises(StageError, match=r"nothing\.csv: file not found"):
        read_rows(tmp_path / "nothing.csv")


def test_json_that_does_not_parse_is_named_at_its_line(tmp_path: Path) -> None:
    path = tmp_path / "x.json"
    path.write_text('{\n  "a": 1,\n  b: 2\n}\n', encoding="utf-8")
    with pytest.raises(StageError, match=r"model .*x\.json:3: not valid JSON \(at column 3\)"):
        read_json(path, what="model")
    path.write_text('[{"a": 1}]', encoding="utf-8")
    assert read_json(path) == [{"a": 1}]
