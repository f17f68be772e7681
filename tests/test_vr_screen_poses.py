"""How participants moved while VR screens waited for an answer (issue 51.3): the head's
yaw/pitch/roll ranges (a turn across +-180 deg is 20 deg, not 340), its travel and the
controllers' path per screen, the summary per screen kind, and the tables an analysis of
sessions with ``_screen_poses.jsonl`` files writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pytest

from facelab.analysis.vr_screen_poses import screen_pose_summary, screen_pose_table
from facelab.experiment.cli import main
from facelab.resources import package_file

KATO = Path(package_file("facelab.protocols", "kato2021.yaml"))


def _record(trial: int, screen: str, yaws: list[float], *, lean_m: float = 0.0) -> dict:
    n = len(yaws)
    head = [[0.1 * k, 0.0, 1.2, lean_m * k / max(1, n - 1), yaw, 2.0 * (k % 2), 0.0]
            for k, yaw in enumerate(yaws)]  # fmt: skip
    hands = [[0.1 * k, hand, 0.3 * hand, 1.0, -0.4 + 0.01 * k * hand, 0.0, 0.0, 0.0]
             for k in range(n) for hand in (0, 1)]  # fmt: skip
    return {"trial_index": trial, "screen": screen, "item": "naturalness", "role": None,
            "shown": 0.0, "viewer_poses": head, "controller_poses": hands,
            "participant": "P01", "session": 1}  # fmt: skip


def test_each_screen_s_movement_is_measured() -> None:
    records = [
        _record(1, "vas", [170.0, 178.0, -175.0, -170.0], lean_m=0.05),  # across +-180
        _record(2, "vas", [0.0, 5.0, -5.0]),
        _record(0, "text", [10.0, 10.0]) | {"role": "instructions", "item": None},
        _record(3, "vas", []),  # answered before a frame was drawn: no row
        _record(4, "vas", [1.0, 2.0]) | {"viewer_poses": [[0.0, "x", 1, 2, 3, 4, 5]]},
    ]
    table = screen_pose_table(records)
    assert list(table["trial_index"]) == [1, 2, 0]
    first = table.iloc[0]
    assert first["head_yaw_range_deg"] == pytest.approx(20.0)
    assert first["head_pitch_range_deg"] == pytest.approx(2.0)
    assert first["head_travel_m"] == pytest.approx(0.05)
    assert first["seconds"] == pytest.approx(0.3) and first["poses"] == 4
    assert first["controllers"] == 2
    assert first["controller_path_m"] == pytest.approx(0.03)  # the right hand moved 3 x 1 cm
    assert table.iloc[1]["head_yaw_range_deg"] == pytest.approx(10.0)
    summary = screen_pose_summary(table).set_index("screen")
    assert summary.loc["vas", "screens"] == 2
    assert summary.loc["vas", "max_head_yaw_range_deg"] == pytest.approx(20.0)
    assert summary.loc["vas", "median_head_yaw_range_deg"] == pytest.approx(15.0)
    assert summary.loc["text", "median_head_yaw_range_deg"] == pytest.approx(0.0)
    assert screen_pose_table([{"viewer_poses": "no"}]).empty


def test_an_analysis_writes_the_screen_pose_tables(tmp_path: Path, capsys) -> None:
    results = tmp_path / "results"
    assert main(["simulate", str(KATO), "--participants", "2", "--sim-seed", "2",
                 "--results", str(results)]) == 0  # fmt: skip
    tsv = next(results.rglob("sub-P01_*_beh.tsv"))
    poses = tsv.with_name(tsv.name.replace("_beh.tsv", "_screen_poses.jsonl"))
    lines = [_record(1, "vas", [0.0, 30.0]), _record(1, "vas", [0.0, 4.0]) | {"participant": "P99"}]
    poses.write_text("".join(json.dumps(r) + "\n" for r in lines) + '{"cut off', "utf-8")
    out = tmp_path / "report"
    assert main(["analyze", str(KATO), str(results), "--out", str(out)]) == 0
    capsys.readouterr()
    with (out / "vr_screen_poses.csv").open(encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert [float(r["head_yaw_range_deg"]) for r in rows] == [30.0, 4.0]
    assert {r["participant"] for r in rows} == {"P01"}  # the session's own, not the record's
    with (out / "vr_screen_poses_summary.csv").open(encoding="utf-8") as f:
        (vas,) = list(csv.DictReader(f))
    assert vas["screen"] == "vas" and vas["screens"] == "2"
    assert "VR screens" in (out / "report.md").read_text(encoding="utf-8")
