"""End to end: `facelab demo` at reduced size, and the consistency of everything it writes."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import pandas as pd
import pytest

from facelab.analysis.load import load_results
from facelab.experiment.cli import main
from facelab.hashing import sha256_file

pytestmark = pytest.mark.slow


def test_demo_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--size", "160x90", "--fps", "5", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "[4/4]" in printed and "done in" in printed and "SIMULATED" in printed

    # clips: every one listed exists with its hash; contact sheets per condition
    rows = list(
        csv.DictReader((out / "clips" / "clips.csv").read_text(encoding="utf-8").splitlines())
    )
    assert len(rows) == 6  # 2 stimuli x 3 conditions (the practice clip is one of them)
    for r in rows:
        assert sha256_file(out / "clips" / r["path"]) == r["sha256"]
        assert (r["width"], r["height"], r["fps"]) == ("160", "90", "5")
    for cond in ("baseline", "standard", "emphasized"):
        assert (out / "clips" / f"contact_{cond}.png").stat().st_size > 10_000

    # sessions: 8 simulated participants x 36 ratings through the session log
    run = next(out.glob("run-*"))
    data = load_results(run / "results")
    assert data["participant"].nunique() == 8 and len(data) == 288 and data["simulated"].all()
    for sidecar in (run / "results").rglob("*_session.json"):
        assert json.loads(sidecar.read_text())["simulated"] is True

    # analysis: the ratings it used are exactly the logged ones
    analysed = pd.read_csv(run / "analysis" / "ratings.csv")
    key = ["participant", "trial_index", "item"]
    merged = analysed.merge(data, on=key, suffixes=("_a", "_l"))
    assert len(analysed) == len(data) == len(merged)
    assert (merged["rating_a"] - merged["rating_l"]).abs().max() < 1e-9
    cells = pd.read_csv(run / "analysis" / "cell_means.csv")
    assert len(cells) == 2 * 2 * 8 * 3  # items x sets x participants x conditions
    layout = pd.read_csv(run / "analysis" / "paper_layout.csv")
    assert set(layout["procedure"]) == {"rm", "paper"} and len(layout) == 8
    report = (run / "analysis" / "report.html").read_text(encoding="utf-8")
    assert "SIMULATED DATA" in report and report.count("data:image/png;base64,") == 4
    assert "0.0053" in report  # the paper's reported values beside facelab's
    # the clips' stimulus checks are a section of the report, every check and condition
    checks = pd.read_csv(out / "clips" / "stimulus_checks.csv", keep_default_na=False)
    assert "<h2>Stimulus checks</h2>" in report
    section = report.split("<h2>Stimulus checks</h2>", 1)[1].split("<h2>", 1)[0]
    for check in set(checks["check"][checks["passed"] != ""]):
        assert f"<td>{check}</td>" in section, check
    assert "## Stimulus checks" in (run / "analysis" / "report.md").read_text(encoding="utf-8")

    # a second demo reuses the clips and never touches the first run's sessions
    before = {p: p.read_bytes() for p in run.rglob("*.tsv")}
    assert main(["demo", "--out", str(out), "--size", "160x90", "--fps", "5", "--quiet"]) == 0
    assert "(0 rendered, 6 reused)" in capsys.readouterr().out
    assert {p: p.read_bytes() for p in run.rglob("*.tsv")} == before
    assert len(list(out.glob("run-*"))) == 2


SHIPPED = sorted(p.stem for p in (Path(__file__).parents[1] / "protocols").glob("*.yaml"))


@pytest.mark.parametrize("name", SHIPPED)
def test_demo_runs_every_shipped_protocol(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`facelab demo --protocol` goes through the one analysis pipeline for every kind of
    study (VAS, 2AFC, staircases, QUEST+, identification, impression, behaviour): the same
    report `facelab analyze` writes, with every response of the simulated sessions in it."""
    from facelab.resources import protocol_path

    out = tmp_path / name
    argv = ["demo", str(protocol_path(name)), "--out", str(out), "--participants",
            "3", "--size", "96x64", "--fps", "5", "--quiet"]  # fmt: skip
    assert main(argv) == 0
    printed = capsys.readouterr().out
    run = next(out.glob("run-*"))
    data = load_results(run / "results")
    assert data["participant"].nunique() == 3
    assert f"[4/4] analysed {len(data)} responses" in printed
    report = (run / "analysis" / "report.html").read_text(encoding="utf-8")
    assert "SIMULATED DATA" in report and "data:image/png;base64," in report
