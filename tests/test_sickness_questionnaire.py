"""The Simulator Sickness Questionnaire (issue 51.2): scoring against the published maxima and
subscale membership, the protocol key, the screens in the timeline and on resume, the log
rows, the analysis tables and what analysis refuses."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from facelab import sickness_questionnaire as ssq
from facelab.analysis.pipeline import run as analyze_run
from facelab.design import build_trials
from facelab.errors import AnalysisError
from facelab.experiment.simulate import simulate_study
from facelab.experiment.timeline import SsqScreen, TextScreen, compile_timeline, remaining
from facelab.protocol import load_protocol
from facelab.resources import protocol_path
from tests.protocol_edits import kato_short, protocol_problems


def _with_ssq(text: str, moments: str = "[before, after]") -> str:
    return text.replace("presentation:\n  language: ja\n",
                        f"presentation:\n  language: ja\n  ssq: {moments}\n", 1)  # fmt: skip


def test_scores_reach_the_published_maxima_and_each_subscale_has_seven_symptoms() -> None:
    """Kennedy et al. (1993): N 200.34, O 159.18, D 292.32, total 235.62 when every symptom
    is severe; 0 when none; each subscale sums seven symptoms."""
    worst = ssq.scores({s.id: 3 for s in ssq.SYMPTOMS})
    assert (worst["N"], worst["O"], worst["D"], worst["total"]) == pytest.approx(
        (200.34, 159.18, 292.32, 235.62)
    )
    assert set(ssq.scores({s.id: 0 for s in ssq.SYMPTOMS}).values()) == {0.0}
    for scale in "NOD":
        assert sum(scale in s.subscales for s in ssq.SYMPTOMS) == 7
    # nausea loads on N and D: one "slight" gives 9.54, 0, 13.92 and (1 + 1) x 3.74
    one = ssq.scores({s.id: int(s.id == "nausea") for s in ssq.SYMPTOMS})
    assert (one["N"], one["O"], one["D"], one["total"]) == pytest.approx((9.54, 0, 13.92, 7.48))


@pytest.mark.parametrize(
    ("answers", "message"),
    [
        ({s.id: 0 for s in ssq.SYMPTOMS[1:]}, "'general_discomfort' has no answer"),
        ({**{s.id: 0 for s in ssq.SYMPTOMS}, "hiccups": 1}, "unknown SSQ symptom 'hiccups'"),
        ({**{s.id: 0 for s in ssq.SYMPTOMS}, "nausea": 4}, "'nausea': expected 0-3, got 4"),
    ],
)
def test_scores_refuse_what_is_not_a_questionnaire(answers, message) -> None:
    with pytest.raises(ValueError, match=message):
        ssq.scores(answers)


def test_the_protocol_key_names_each_moment_once(tmp_path: Path) -> None:
    text = protocol_path("kato2021").read_text(encoding="utf-8")
    problem = protocol_problems(_with_ssq(text, "[after, after]"), tmp_path)
    assert "presentation.ssq" in problem and "named once" in problem
    problem = protocol_problems(_with_ssq(text, "[during]"), tmp_path)
    assert "presentation.ssq" in problem and "'before' or 'after'" in problem


def test_the_questionnaire_opens_and_closes_the_session_and_resumes_where_it_stopped(
    tmp_path: Path,
) -> None:
    path = tmp_path / "kato.yaml"
    path.write_text(_with_ssq(protocol_path("kato2021").read_text(encoding="utf-8")), "utf-8")
    protocol = load_protocol(path)
    trials = build_trials(protocol, participant="P01")
    screens = compile_timeline(protocol, trials, participant="P01", session=1)
    kinds = [s.kind if not isinstance(s, TextScreen) else s.role for s in screens]
    assert kinds[:18] == ["welcome", *["ssq"] * 16, "instructions"]
    assert kinds[-17:] == [*["ssq"] * 16, "end"]
    before = [s for s in screens[1:17] if isinstance(s, SsqScreen)]
    assert [s.symptom for s in before] == [s.id for s in ssq.SYMPTOMS]
    assert {s.moment for s in before} == {"before"}
    assert before[7].question("ja") == (
        "【吐き気】いまのあなたの状態について、この症状はどのくらいありますか。"
    )
    assert [label for _, label in before[0].choices("en")] == ["None", "Slight", "Moderate",
                                                               "Severe"]  # fmt: skip
    # every key of the session is distinct: the questionnaire's items carry their moment
    keys = [k for s in screens for k in s.response_keys()]
    assert len(keys) == len(set(keys)) == 32 + 18 * 2
    # answered: the first five symptoms before; resume shows the other eleven first
    answered = {k for s in before[:5] for k in s.response_keys()}
    todo = remaining(screens, answered, language="ja")
    shown = [s for s in todo if isinstance(s, SsqScreen) and s.moment == "before"]
    assert [s.symptom for s in shown] == [s.id for s in ssq.SYMPTOMS[5:]]
    assert isinstance(todo[1], TextScreen) and todo[1].role == "resume"
    assert todo[2] == before[5]


@pytest.mark.slow
def test_simulated_sessions_are_scored_and_a_missing_answer_is_named(tmp_path: Path) -> None:
    path = tmp_path / "kato.yaml"
    path.write_text(_with_ssq(kato_short(protocol_path("kato2021").read_text("utf-8"))), "utf-8")
    protocol = load_protocol(path)
    results = tmp_path / "results"
    simulate_study(protocol, protocol_path=path, results=results, participants=4, seed=3)
    run = analyze_run(results, protocol, out=tmp_path / "a", protocol_path=path)
    assert run.check.sessions["complete"].all()
    table = run.tasks.tables["ssq"]
    assert len(table) == 8 and set(table["moment"]) == {"before", "after"}
    logs = sorted(results.rglob("*_beh.tsv"))
    # recompute one questionnaire from its log rows
    rows = list(csv.DictReader(logs[0].open(encoding="utf-8"), delimiter="\t"))
    mine = {r["stimulus"]: int(r["response"]) for r in rows
            if r["screen"] == "ssq" and r["condition"] == "after"}  # fmt: skip
    assert len(mine) == 16
    got = table[(table["participant"] == "P01") & (table["moment"] == "after")].iloc[0]
    assert got["total"] == pytest.approx(ssq.scores(mine)["total"])
    summary = run.tasks.tables["ssq_summary"]
    change = summary[summary["moment"].str.startswith("change")].set_index("score")
    wide = table.pivot(index="participant", columns="moment", values="total")
    assert change.loc["total", "mean"] == pytest.approx((wide["after"] - wide["before"]).mean())
    assert change.loc["total", "n"] == 4
    report = (tmp_path / "a" / "report.html").read_text(encoding="utf-8")
    assert "Simulator sickness" in report and "ssq_summary" in report
    # one answer missing from P02's questionnaire after: not scored, named, session incomplete
    log = next(p for p in logs if "sub-P02" in p.name)
    lines = log.read_text(encoding="utf-8").splitlines()
    log.write_text("\n".join(x for x in lines if "ssq_after_vertigo" not in x) + "\n", "utf-8")
    run = analyze_run(results, protocol, out=tmp_path / "b", protocol_path=path)
    got = run.tasks.tables["ssq"].set_index(["participant", "moment"])
    assert np.isnan(got.loc[("P02", "after"), "total"])
    assert got.loc[("P02", "after"), "symptoms_answered"] == 15
    assert any("SSQ after of P02" in n and "15 of 16" in n for n in run.tasks.notes)
    assert not run.check.sessions.set_index("participant").loc["P02", "complete"]
    change = run.tasks.tables["ssq_summary"]
    assert change[change["moment"].str.startswith("change")]["n"].eq(3).all()


def test_questionnaire_answers_under_a_protocol_without_it_are_refused(tmp_path: Path) -> None:
    text = kato_short(protocol_path("kato2021").read_text("utf-8"))
    asked = tmp_path / "asked.yaml"
    asked.write_text(_with_ssq(text, "[after]"), "utf-8")
    results = tmp_path / "results"
    simulate_study(load_protocol(asked), protocol_path=asked, results=results, participants=1,
                   seed=1)  # fmt: skip
    plain = tmp_path / "plain.yaml"
    plain.write_text(text, "utf-8")
    with pytest.raises(AnalysisError, match=r"items ssq_after_blurred_vision, .* that the "
                       r"protocol 'kato2021' does not have"):  # fmt: skip
        analyze_run(results, load_protocol(plain), out=tmp_path / "a",
                    protocol_path=plain, accept_protocol_change=True)  # fmt: skip


def test_stopped_inside_the_questionnaire_before_the_study_still_gets_its_instructions(
    tmp_path: Path,
) -> None:
    """Three symptoms answered, then the page reloaded: the other thirteen, then the
    instructions and the practice trial, which the participant has not seen yet."""
    path = tmp_path / "kato.yaml"
    path.write_text(_with_ssq(protocol_path("kato2021").read_text(encoding="utf-8")), "utf-8")
    protocol = load_protocol(path)
    screens = compile_timeline(protocol, build_trials(protocol, participant="P01"),
                               participant="P01", session=1)  # fmt: skip
    answered = {k for s in screens[1:4] for k in s.response_keys()}
    todo = remaining(screens, answered, language="ja")
    roles = [s.role for s in todo if isinstance(s, TextScreen)]
    assert roles[:4] == ["welcome", "resume", "instructions", "practice"]
    assert [s.symptom for s in todo[2:15]] == [s.id for s in ssq.SYMPTOMS[3:]]
    assert len(todo) == len(screens) - 3 + 1


def _one_session_with_ssq_after(tmp_path: Path):
    """(protocol path, protocol, results root, the log) of one simulated participant of
    kato2021 (short) with the questionnaire after the trials."""
    path = tmp_path / "kato.yaml"
    path.write_text(_with_ssq(kato_short(protocol_path("kato2021").read_text("utf-8")),
                              "[after]"), "utf-8")  # fmt: skip
    protocol = load_protocol(path)
    results = tmp_path / "results"
    simulate_study(protocol, protocol_path=path, results=results, participants=1, seed=2)
    return path, protocol, results, next(results.rglob("*_beh.tsv"))


@pytest.mark.parametrize(
    ("column", "value", "message"),
    [
        ("trial_index", "5", "trial_index is 5, expected 0"),
        ("condition", "before", "condition is 'before', expected 'after'"),
        ("response", "2.5", "response '2.5', expected 0, 1, 2 or 3"),
        ("screen", "identify", "a sickness questionnaire item on screen 'identify'"),
    ],
)
def test_an_edited_questionnaire_row_is_refused(tmp_path: Path, column, value, message) -> None:
    path, protocol, results, log = _one_session_with_ssq_after(tmp_path)
    rows = list(csv.DictReader(log.open(encoding="utf-8"), delimiter="\t"))
    target = next(r for r in rows if r["item"] == "ssq_after_nausea")
    target[column] = value
    with log.open("w", encoding="utf-8", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]), delimiter="\t", lineterminator="\n")
        writer.writeheader()
        writer.writerows(rows)
    with pytest.raises(AnalysisError, match="ssq_after_nausea") as info:
        analyze_run(results, protocol, out=tmp_path / "a", protocol_path=path)
    assert message in str(info.value)


def test_a_vas_row_relabelled_as_the_questionnaire_is_refused(tmp_path: Path) -> None:
    path, protocol, results, log = _one_session_with_ssq_after(tmp_path)
    lines = log.read_text(encoding="utf-8").splitlines()
    header = lines[0].split("\t")
    first = lines[1].split("\t")
    first[header.index("screen")] = "ssq"
    log.write_text("\n".join([lines[0], "\t".join(first), *lines[2:]]) + "\n", "utf-8")
    with pytest.raises(AnalysisError, match="screen ssq but not a questionnaire item"):
        analyze_run(results, protocol, out=tmp_path / "a", protocol_path=path)
