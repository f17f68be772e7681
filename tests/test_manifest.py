"""clips.csv written atomically; partial renders keep the rows of clips rendered earlier."""

from __future__ import annotations

import csv
from pathlib import Path

from facelab.formats import write_manifest

COLUMNS = ("clip_id", "path", "level")


def _rows(out: Path) -> list[dict]:
    return list(csv.DictReader((out / "clips.csv").read_text(encoding="utf-8").splitlines()))


def _clip(out: Path, clip_id: str, level: float) -> dict:
    (out / f"{clip_id}.mp4").write_bytes(b"x")
    return {"clip_id": clip_id, "path": f"{clip_id}.mp4", "level": level}


def test_merge_keeps_present_clips_and_replaces_re_rendered_ones(tmp_path: Path) -> None:
    first = [_clip(tmp_path, c, i) for i, c in enumerate(("a", "b", "c"))]
    assert write_manifest(tmp_path, first, columns=COLUMNS, merge=True) == []
    (tmp_path / "c.mp4").unlink()
    notes = write_manifest(tmp_path, [_clip(tmp_path, "b", 9)], columns=COLUMNS, merge=True)
    assert [(r["clip_id"], r["level"]) for r in _rows(tmp_path)] == [("a", "0"), ("b", "9")]
    assert any("kept 1 clip" in n for n in notes)
    assert any("file is gone: c" in n for n in notes)
    assert not (tmp_path / "clips.csv.tmp").exists()


def test_without_merge_or_with_other_columns_rows_are_replaced(tmp_path: Path) -> None:
    write_manifest(tmp_path, [_clip(tmp_path, "a", 0)], columns=COLUMNS)
    write_manifest(tmp_path, [_clip(tmp_path, "b", 1)], columns=COLUMNS)
    assert [r["clip_id"] for r in _rows(tmp_path)] == ["b"]
    other = ("clip_id", "path", "emotion")
    notes = write_manifest(
        tmp_path, [{"clip_id": "z", "path": "z.mp4", "emotion": "joy"}], columns=other, merge=True
    )
    assert [r["clip_id"] for r in _rows(tmp_path)] == ["z"]
    assert any("other columns" in n for n in notes)


def test_unreadable_manifest_is_moved_aside_and_named(tmp_path: Path) -> None:
    (tmp_path / "clips.csv").write_bytes(b"\xff\xfe\x00bad")
    notes = write_manifest(tmp_path, [_clip(tmp_path, "a", 0)], columns=COLUMNS, merge=True)
    assert [r["clip_id"] for r in _rows(tmp_path)] == ["a"]
    assert (tmp_path / "clips.csv.unreadable").read_bytes() == b"\xff\xfe\x00bad"
    assert any("moved it to clips.csv.unreadable" in n for n in notes)


def test_kept_rows_from_another_source_are_named(tmp_path: Path) -> None:
    cols = ("clip_id", "path", "model")
    first = [{**_clip(tmp_path, c, 0), "model": "m1"} for c in ("a", "b")]
    write_manifest(tmp_path, first, columns=cols, merge=True, provenance="model")
    again = [{**_clip(tmp_path, "c", 0), "model": "m1"}]
    assert not any("another model" in n for n in write_manifest(
        tmp_path, again, columns=cols, merge=True, provenance="model"
    ))  # fmt: skip
    other = [{**_clip(tmp_path, "d", 0), "model": "m2"}]
    notes = write_manifest(tmp_path, other, columns=cols, merge=True, provenance="model")
    assert any("3 kept clip(s) have another model than these (a, b, c)" in n for n in notes)
