"""Measured presentation that can fail (issue 51.3): each clip's displayed frames give the
longest time one frame stayed on screen, the freezes and the frames never shown - a frozen
picture the A/V offset cannot see - and ``facelab analyze --exclude-trials RULE`` leaves out
trials by any playback measure, saying how many per condition."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from facelab.analysis.presentation import frame_measures
from facelab.experiment.cli import main
from facelab.resources import protocol_path


def _record(trial: int, *, freeze_s: float = 0.0, yaw: float | None = None, n: int = 30) -> dict:
    """A 1 s clip of 30 frames shown at 60 Hz (each frame on two flips), optionally frozen on
    frame 10 for ``freeze_s`` (the display kept flipping; the picture did not change)."""
    flips, shown, t = [], [], 0.0
    for k in range(n):
        hold = 2 + (round(freeze_s * 60) if k == 10 else 0)
        for _ in range(hold):
            flips.append(round(t, 4))
            shown.append(k)
            t += 1 / 60
    record = {"trial_index": trial, "clip": "0" * 64 + ".mp4", "replay": False, "onset": 1.0,
              "frames_expected": n, "dropped": 0, "flip_times": flips, "frames_shown": shown,
              "media_time_end": 1.0, "display": "live3d", "av_offset_ms": 8.0}  # fmt: skip
    if yaw is not None:
        record["head_yaw_range_deg"] = yaw
    return record


def test_frame_measures_see_a_frozen_picture_and_frames_never_shown() -> None:
    smooth = frame_measures(_record(1))
    assert smooth == {"frame_age_max_ms": pytest.approx(33.33, abs=0.1), "frames_frozen": 0,
                      "frames_never_shown_share": 0.0}  # fmt: skip
    frozen = frame_measures(_record(1, freeze_s=0.5))
    assert frozen["frame_age_max_ms"] == pytest.approx(533.3, abs=0.5)
    assert frozen["frames_frozen"] == 0  # flips went on: a freeze of the picture, not the display
    gap = _record(1)
    gap["flip_times"] = gap["flip_times"][:20] + [t + 0.4 for t in gap["flip_times"][20:]]
    assert frame_measures(gap)["frames_frozen"] == 1
    assert frame_measures(gap)["frame_age_max_ms"] == pytest.approx(433.3, abs=0.5)
    skipped = _record(1)
    keep = [i for i, k in enumerate(skipped["frames_shown"]) if k % 3]
    skipped["flip_times"] = [skipped["flip_times"][i] for i in keep]
    skipped["frames_shown"] = [skipped["frames_shown"][i] for i in keep]
    assert frame_measures(skipped)["frames_never_shown_share"] == pytest.approx(10 / 30, abs=1e-4)
    assert frame_measures({"flip_times": []})["frame_age_max_ms"] is None


def test_analyze_excludes_trials_by_any_playback_measure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """kato2021, 4 simulated sessions, each given playback records: trial 3 frozen for
    0.5 s, trial 5 with a 40° head turn. The rules leave out exactly those trials' ratings
    (2 items each), the report says so per condition and rule; a rule on an unknown measure
    or one that does not parse is refused in words."""
    path = protocol_path("kato2021")
    results = tmp_path / "results"
    assert main(["simulate", str(path), "--participants", "4", "--sim-seed", "5",
                 "--results", str(results)]) == 0  # fmt: skip
    for tsv in sorted(results.rglob("*_beh.tsv")):
        lines = [_record(t, freeze_s=0.5 if t == 3 else 0.0, yaw=40.0 if t == 5 else 4.0)
                 for t in range(1, 19)]  # fmt: skip
        tsv.with_name(tsv.name.replace("_beh.tsv", "_playback.jsonl")).write_text(
            "".join(json.dumps(r) + "\n" for r in lines), encoding="utf-8"
        )
    capsys.readouterr()
    out = tmp_path / "analysis"
    assert main(["analyze", str(path), str(results), "--out", str(out),
                 "--exclude-trials", "frame_age_max_ms > 100",
                 "--exclude-trials", "head_yaw_range_deg > 30"]) == 0  # fmt: skip
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "excluded 8 responses of 4 trials where frame_age_max_ms > 100" in report
    assert "excluded 8 responses of 4 trials where head_yaw_range_deg > 30" in report
    ratings = (out / "ratings.csv").read_text(encoding="utf-8").splitlines()
    assert len(ratings) - 1 == 4 * 36 - 16
    capsys.readouterr()
    for rule, said in (("yaw > 30", "no playback measure 'yaw'"),
                       ("head_yaw_range_deg >> 30", "expected MEASURE OP NUMBER")):  # fmt: skip
        assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "x"),
                     "--exclude-trials", rule]) == 2  # fmt: skip
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err
    # a rule that takes nothing is said too, with why
    assert main(["analyze", str(path), str(results), "--out", str(tmp_path / "none"),
                 "--exclude-trials", "frame_age_max_ms > 10000"]) == 0  # fmt: skip
    report = (tmp_path / "none" / "report.md").read_text(encoding="utf-8")
    assert "trials where frame_age_max_ms > 10000 (--exclude-trials): no trial met it, " \
        "nothing was left out (72 trials measured)" in report


def test_a_rule_on_sessions_that_do_not_record_its_measure_is_said_to_take_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Lab or video sessions record no frame or live measures: --exclude-trials and
    --max-av-offset-ms are applied and the report says they could take nothing, instead of
    a report identical to one without them."""
    path = protocol_path("kato2021")
    results = tmp_path / "results"
    assert main(["simulate", str(path), "--participants", "3", "--sim-seed", "5",
                 "--results", str(results)]) == 0  # fmt: skip
    out = tmp_path / "analysis"
    assert main(["analyze", str(path), str(results), "--out", str(out), "--exclude-trials",
                 "frames_frozen > 0", "--max-av-offset-ms", "45"]) == 0  # fmt: skip
    report = (out / "report.md").read_text(encoding="utf-8")
    printed = capsys.readouterr().out
    for said in ("trials where frames_frozen > 0 (--exclude-trials): no trial of the sessions "
                 "carries this measure, so nothing was left out",
                 "(--max-av-offset-ms; measured only where clips were drawn live, display "
                 "live3d or webxr): no trial of the sessions carries this measure"):  # fmt: skip
        assert said in report and said in printed
