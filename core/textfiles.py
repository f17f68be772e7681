"""Reading users' text files (CSV indexes, tables) with one clear error for every way it fails."""

from __future__ import annotations

import csv
import io
from collections.abc import Sequence
from pathlib import Path

from facelab.errors import FacelabError, StageError

__all__ = ["Rows", "read_json", "read_rows", "read_text"]


def read_text(
    path: Path | str,
    *,
    what: str = "",
    error: type[FacelabError] = StageError,
    encoding: str = "utf-8-sig",
) -> str:
    """The text of ``path`` (UTF-8, a byte-order mark dropped); ``what`` (e.g. "Z matrix")
    starts the error message.

    Raises ``error`` naming the file when it cannot be read or is not UTF-8 text (with the
    offending byte and its position), instead of a ``UnicodeDecodeError`` traceback.
    """
    path = Path(path)
    name = f"{what} {path}" if what else str(path)
    try:
        return path.read_text(encoding=encoding)
    except UnicodeDecodeError as exc:
        byte = exc.object[exc.start : exc.start + 1].hex()
        line = exc.object[: exc.start].count(b"\n") + 1
        raise error(
            f"{name}:{line}: not UTF-8 text (byte 0x{byte}); save it as UTF-8 (CSV UTF-8 in "
            "spreadsheet programs; not Shift-JIS)"
        ) from None
    except IsADirectoryError:
        raise error(f"{name}: is a folder, expected a file") from None
    except FileNotFoundError:
        raise error(f"{name}: file not found") from None
    except OSError as exc:
        raise error(f"{name}: cannot read ({exc.strerror or 'the system refused'})") from None


def read_json(
    path: Path | str, *, what: str = "", error: type[FacelabError] = StageError
) -> object:
    """The JSON value in the file at ``path``; ``error`` names the file and the line and
    column where it stops being JSON (not the parser's wording)."""
    import json

    path = Path(path)
    name = f"{what} {path}" if what else str(path)
    text = read_text(path, what=what, error=error)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise error(f"{name}:{exc.lineno}: not valid JSON (at column {exc.colno})") from None


class Rows(list):
    """A table's rows (dicts, column -> text) as :func:`read_rows` read them, with the
    ``header`` (column names in file order) and each row's line in the file (``lines``)."""

    def __init__(self, header: list[str], rows: list[dict[str, str]], lines: list[int]):
        super().__init__(rows)
        self.header, self.lines = header, lines

    def located(self) -> list[tuple[int, dict[str, str]]]:
        """(line, row) pairs, for messages naming the line."""
        return list(zip(self.lines, self, strict=True))


#: the separators a table may use when :func:`read_rows` is asked to tell them apart
SEPARATORS = {",": "comma", "\t": "tab", ";": "semicolon"}


def read_rows(
    path: Path | str,
    *,
    what: str = "",
    required: Sequence[str] = (),
    expected: str = "",
    delimiter: str | None = ",",
    error: type[FacelabError] = StageError,
) -> Rows:
    """The rows of a CSV table at ``path`` as dicts (column -> text) in a :class:`Rows`
    (with the header and each row's line); blank lines skipped, a byte-order mark dropped.

    Refused with ``error`` naming the file and line (instead of the silent shifts of
    ``csv.DictReader`` and pandas): an empty file, a header naming a column twice or an
    empty one, a row with more or fewer fields than the header (a comma inside an unquoted
    value), a quoted value never closed, and missing ``required`` columns. ``expected``
    describes the columns in messages (default: ``required``). ``delimiter=None`` accepts a
    comma-, tab- or semicolon-separated table, told apart by its header line.
    """
    path = Path(path)
    name = f"{what} {path}" if what else str(path)
    want = expected or ", ".join(required)
    empty = error(f"{name}: empty; expected a header line{f' with {want}' if want else ''}, "
                  "then rows")  # fmt: skip
    text = read_text(path, what=what, error=error)
    first = next((ln for ln in text.splitlines() if ln.strip()), None)
    if first is None:
        raise empty
    if delimiter is None:
        delimiter = max(SEPARATORS, key=first.count)
    # the text as one stream: a quoted value may hold a line break, and only \n and \r end
    # a line (not the other characters str.splitlines() splits at)
    reader = csv.reader(io.StringIO(text, newline=""), delimiter=delimiter, strict=True)
    header: list[str] | None = None
    rows: list[dict[str, str]] = []
    at: list[int] = []  # the line each row starts on
    start = 1
    try:
        for fields in reader:
            line, start = start, reader.line_num + 1
            if not any(f.strip() for f in fields):
                continue
            if header is None:
                header = [f.strip() for f in fields]
                # separators ending the header line (some exporters end every line with one,
                # spreadsheets add the empty columns of their used range) name no column
                while len(header) > 1 and header[-1] == "":
                    header.pop()
                _check_header(header, name=f"{name}:{line}", error=error)
                missing = [c for c in required if c not in header]
                if missing:
                    raise error(
                        f"{name}:{line}: missing column(s) {', '.join(missing)}; "
                        f"expected {want} in the header line"
                    )
                continue
            # empty fields past the header's last column: a separator ending the line
            while len(fields) > len(header) and not fields[-1].strip():
                fields = fields[:-1]
            if len(fields) != len(header):
                raise error(
                    f"{name}:{line}: {len(fields)} fields, the header has "
                    f"{len(header)} (put a value that contains a "
                    f"{SEPARATORS.get(delimiter, repr(delimiter))} between double quotes)"
                )
            rows.append(dict(zip(header, fields, strict=True)))
            at.append(line)
    except csv.Error:
        raise error(
            f"{name}:{start}: a value's double quotes are not closed by the end of the file, "
            "or text follows a closing quote"
        ) from None
    if header is None:  # only separators and spaces
        raise empty
    return Rows(header, rows, at)


def _check_header(header: list[str], *, name: str, error: type[FacelabError]) -> None:
    """Refuse a header naming a column twice or leaving one unnamed."""
    if any(not h for h in header):
        raise error(f"{name}: a column has no name in the header line")
    twice = sorted({h for h in header if header.count(h) > 1})
    if twice:
        raise error(f"{name}: column(s) named twice in the header: {', '.join(twice)}")
