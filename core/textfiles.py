"""Reading users' text files (CSV indexes, tables) with one clear error for every way it fails."""

from __future__ import annotations

from pathlib import Path

from facelab.errors import FacelabError, StageError

__all__ = ["read_text"]


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
        raise error(
            f"{name}: not UTF-8 text (byte 0x{byte} at position {exc.start}); "
            "save it as UTF-8 (CSV UTF-8 in spreadsheet programs)"
        ) from None
    except OSError as exc:
        raise error(f"{name}: cannot read ({exc.strerror or exc})") from None
