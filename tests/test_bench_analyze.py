"""`facelab bench analyze` times the analysis of a simulated study; a choice-only protocol
(no rating items for the mixed-model check) is benchmarked too, not refused with a
traceback."""

from __future__ import annotations

import json

import pytest

from facelab.experiment.cli import main
from facelab.resources import protocol_path


@pytest.mark.slow
def test_bench_analyze_times_a_choice_only_protocol(capsys: pytest.CaptureFixture[str]) -> None:
    path = protocol_path("gain_2afc")
    assert main(["bench", "analyze", str(path), "--participants", "2", "--runs", "1"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["responses"] == 2 * 60 and len(report["analyze_s_runs"]) == 1
    assert report["lmm_f_closed_form_50"] is None and report["lmm_f_relative_difference"] is None
    fc = report["forced_choice"]
    assert fc["participants"] == 8 and fc["analyze_s"] > 0
