"""Typed answers and the Brand & Kollmeier procedure (issue 52.2): a ``typed`` task collects
what the participant heard as text, stored as typed and scored as pronounced (``score``: the
share of keywords or morae reproduced); ``rule: brand_kollmeier`` moves the SNR after each
sentence by its score's distance from the target. ``protocols/kato2021_srt_sentences.yaml``
runs both with kato2021's methods; simulated listeners' thresholds are recovered from the
keywords they typed, in the lab window (real X key events, Japanese characters) and online
(Chromium)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from facelab.analysis import srt
from facelab.design import Trial
from facelab.errors import SessionError
from facelab.experiment.simulate import simulated_rows
from facelab.experiment.timeline import AnswerError, TypedScreen, compile_timeline, typed_text
from facelab.protocol import load_protocol, load_protocol_text
from facelab.resources import protocol_path
from facelab.sessionlog import LOG_COLUMNS, LOG_COLUMNS_V2, SessionContext, SessionLog
from facelab.staircase import BrandKollmeierStaircase, new_staircase
from tests.protocol_edits import protocol_problems

SERIES = ["audio", "baseline", "emphasized"]


def _protocol():
    return load_protocol(protocol_path("kato2021_srt_sentences"))


def _problems(text: str, tmp_path) -> str:
    return protocol_problems(text, tmp_path, "p.yaml")


def _typed_screen(protocol, stimulus: str = "s02") -> TypedScreen:
    trial = Trial(trial_index=1, block="audio", set_index=1, stimulus_set="sentences",
                  stimulus=stimulus, condition="audio_m4", repetition=1)  # fmt: skip
    from facelab.experiment.timeline import trial_screens

    (_, screen) = trial_screens(protocol, trial)
    assert isinstance(screen, TypedScreen)
    return screen


def test_the_typed_screen_stores_the_text_as_typed_and_its_score() -> None:
    protocol = _protocol()
    screen = _typed_screen(protocol)
    assert screen.said == "古い本を三冊買う。"
    assert screen.keywords == ("古い", "本", "三冊", "買う")
    # whitespace runs (tabs, newlines, ideographic spaces) become one space; NFC
    assert typed_text(" ふるい\tほん\u3000\u3000さんさつ\nかう ") == "ふるい ほん さんさつ かう"
    assert typed_text("か\u3099う") == "がう"
    answer = screen.answer("sentence", {"text": "古い本を3冊\t飼う"}, rt_s=2.0,
                           timestamp="2026-11-27T00:00:00+00:00")  # fmt: skip
    assert answer.text == "古い本を3冊 飼う"
    ctx = SessionContext(study="s", participant="P1", session=1, simulated=False,
                         protocol_sha256="0" * 64)  # fmt: skip
    row = screen.row("sentence", answer, context=ctx, playback=None)
    # 飼う is read カウ like 買う: scored as pronounced, every keyword right
    assert (row["response"], row["score"], row["correct"]) == ("古い本を3冊 飼う", 1.0, 1)
    def row_of(text: str) -> dict:
        answer = screen.answer("sentence", {"text": text}, rt_s=1.0, timestamp="t")
        return screen.row("sentence", answer, context=ctx, playback=None)

    half = row_of("ふるいほん")
    assert (half["score"], half["correct"]) == (0.5, 0)
    empty = row_of("  ")
    assert (empty["response"], empty["score"], empty["correct"]) == (None, 0.0, 0)
    for posted, problem in (({"text": 3}, "expected the typed text"),
                            ({}, "expected the typed text"),
                            ({"text": "あ" * 81}, "81 characters, at most 80")):  # fmt: skip
        with pytest.raises(AnswerError, match=problem):
            screen.answer("sentence", posted, rt_s=1.0, timestamp="2026-11-27T00:00:00+00:00")


def test_the_sentences_protocol_runs_one_adaptive_track_per_series() -> None:
    protocol = _protocol()
    screens = compile_timeline(protocol, [], participant="P1", session=1)
    assert screens  # compiles without trials too
    assert [b.staircase.rule for b in protocol.blocks] == ["brand_kollmeier"] * 3
    state = new_staircase(protocol, "audio")
    assert isinstance(state, BrandKollmeierStaircase)
    assert state.condition == "audio_p2" and state.levels[0] == 2.0 and state.levels[-1] == -16.0


def test_brand_kollmeier_steps_by_the_score_and_shrinks_at_reversals() -> None:
    """ΔL = -f(i) (score - 0.5) / 0.15 with f(i) = 1.5 x 1.41^-i after i reversals (levels
    in dB, higher easier); the level shown is the grid's nearest to the tracked one."""
    grid = tuple(f"c{k}" for k in range(21))
    levels = tuple(float(10 - k) for k in range(21))  # +10 .. -10 dB, 1 dB apart
    st = BrandKollmeierStaircase(grid=grid, levels=levels, start=0)
    assert st.update(True, 1.0) is False  # all words: 1.5 * 0.5 / 0.15 = 5 dB harder
    assert st.value == pytest.approx(5.0) and st.level == 5.0
    assert st.update(False, 0.75) is False  # 1.5 * 0.25 / 0.15 = 2.5 dB harder
    assert st.value == pytest.approx(2.5) and st.level in (2.0, 3.0)
    assert st.update(False, 0.0) is True  # easier now: a reversal, f = 1.5 / 1.41 from here
    assert st.value == pytest.approx(2.5 + 1.5 * 0.5 / 0.15)
    assert st.step_factor() == pytest.approx(1.5 / 1.41)
    before = st.value
    st.update(True, 0.5)  # at the target: no move
    assert st.value == pytest.approx(before)
    for _ in range(30):  # the floor: f never below f_min
        st.update(True, 1.0)
        st.update(False, 0.0)
    assert st.step_factor() == pytest.approx(0.1)
    assert -10.0 <= st.value <= 10.0
    # lower easier: the same answers move the other way
    low = BrandKollmeierStaircase(grid=grid, levels=levels[::-1], start=0, sign=-1)
    low.update(True, 1.0)
    assert low.value == pytest.approx(-10.0 + 5.0)


def test_the_track_is_rebuilt_from_the_logged_scores() -> None:
    protocol = _protocol()
    rows = simulated_rows(protocol, participant="P1", rng=np.random.default_rng(7))
    audio = sorted((r for r in rows if r["block"] == "audio"), key=lambda r: r["trial_index"])
    assert len(audio) == 20 and all(0.0 <= r["score"] <= 1.0 for r in audio)
    assert any(0.0 < r["score"] < 1.0 for r in audio)  # partial sentences move it less
    state = new_staircase(protocol, "audio")
    steps = state.replay((r["trial_index"], r["condition"], bool(r["correct"]), r["score"])
                         for r in audio)  # fmt: skip
    shown = [r["condition"] for r in audio]
    assert [s["next_condition"] for s in steps[:-1]] == shown[1:]
    assert len(set(shown)) >= 4  # it moved over the grid


def test_thresholds_are_recovered_from_typed_keywords() -> None:
    protocol = _protocol()
    rows = []
    for k in range(12):
        rows += simulated_rows(protocol, participant=f"P{k + 1:03d}",
                               rng=np.random.default_rng([5, k]))  # fmt: skip
    frame = pd.DataFrame(rows)
    table = srt.srt_table(frame, protocol, protocol.tasks[0])
    assert list(table["condition"].unique()) == SERIES
    # 20 sentences of 3 or 4 keywords per series: every keyword counted
    assert table["n"].between(60, 80).all()
    summary, _ = srt.srt_tests(table, reference="audio")
    truth = protocol.simulation.srt
    for r in summary.itertuples():
        half = (r.srt_db_ci_high - r.srt_db_ci_low) / 2
        assert abs(r.srt_db_mean - truth[r.condition].srt_db) <= 1.5 * half, r


def _coverage(protocol, *, participants: int, seed: int) -> dict[str, float]:
    truths = {s: t.model_copy(update={"srt_sd_db": 0.0})
              for s, t in protocol.simulation.srt.items()}  # fmt: skip
    protocol = protocol.model_copy(update={"simulation": protocol.simulation.model_copy(
        update={"srt": truths})})  # fmt: skip
    rows = []
    for k in range(participants):
        rows += simulated_rows(protocol, participant=f"P{k + 1:03d}",
                               rng=np.random.default_rng([seed, k]))  # fmt: skip
    table = srt.srt_table(pd.DataFrame(rows), protocol, protocol.tasks[0])
    out = {}
    for series, part in table.groupby("condition"):
        want = truths[series].srt_db
        out[series] = float(((part["srt_ci_low"] <= want) & (want <= part["srt_ci_high"])).mean())
    return out


@pytest.mark.slow
def test_each_participants_srt_from_a_brand_kollmeier_track_covers_the_truth() -> None:
    """150 simulated participants per series, 20 sentences each: coverage of the 95 % profile
    intervals fitted to every keyword - reported. Below the nominal rate: measured 0.87,
    0.90, 0.93 (seed 52; 30 sentences: 0.85-0.91) - the track stays near the threshold, so
    the slope is overestimated (median 0.165 per dB against the true 0.12) and the SRT's
    profile is too narrow; held to 0.85-0.98 so that a worse fit fails, and named in the
    README (constant stimuli reach the nominal rate)."""
    coverage = _coverage(_protocol(), participants=150, seed=52)
    print(f"SRT interval coverage, Brand-Kollmeier tracks of typed sentences: {coverage}")
    assert set(coverage) == set(SERIES)
    assert all(0.85 <= v <= 0.98 for v in coverage.values()), coverage


def test_typed_tasks_and_the_rule_are_checked_with_their_keys(tmp_path) -> None:
    text = protocol_path("kato2021_srt_sentences").read_text(encoding="utf-8")
    vr = text.replace("  language: ja\n", "  language: ja\n  display: webxr\n", 1)
    assert "typed answers need a keyboard" in _problems(vr, tmp_path)
    wrong = text.replace("      s01: [赤い, 車, 止まった]", "      s99: [赤い, 車, 止まった]")
    assert "tasks[0].keywords.s99: unknown stimulus 's99'" in _problems(wrong, tmp_path)
    silent = text.replace("{id: s10, text: 静かな部屋で読む。}",
                          "{id: s10, audio: s10.wav}")  # fmt: skip
    (tmp_path / "s10.wav").write_bytes(b"")
    assert "stimulus 's10' of set 'sentences' has no text or transcript" in _problems(
        silent, tmp_path)  # fmt: skip
    mixed = text.replace("rule: brand_kollmeier, start: audio_p2,",
                         "rule: up_down, start: audio_p2, assumed_slope: 0.2,")  # fmt: skip
    assert "'assumed_slope' belongs to rule brand_kollmeier, not 'up_down'" in _problems(
        mixed, tmp_path)  # fmt: skip
    nostart = text.replace("rule: brand_kollmeier, start: audio_p2,", "rule: brand_kollmeier,")
    assert "rule 'brand_kollmeier' needs a 'start'" in _problems(nostart, tmp_path)


def test_a_log_begun_before_scores_goes_on_in_its_own_columns(tmp_path) -> None:
    """A session begun by a facelab whose log had no ``score`` column is resumed and
    continued in its columns; an answer that needs a score is refused there, nothing
    written."""
    log = SessionLog.create(tmp_path, study="s", participant="P1", session=1, provenance={})
    old_header = "\t".join(LOG_COLUMNS_V2) + "\n"
    log.paths.tsv.write_text(old_header, encoding="utf-8")
    resumed = SessionLog.resume(tmp_path, study="s", participant="P1", session=1)
    assert resumed.columns == LOG_COLUMNS_V2
    row = {c: None for c in LOG_COLUMNS} | {
        "study": "s", "participant": "P1", "session": 1, "trial_index": 1, "item": "vas",
        "rating": 50.0, "rt_s": 1.0, "timestamp": "2026-12-07T09:00:00.000+00:00",
        "simulated": False,
    }  # fmt: skip
    resumed.append(row)
    lines = log.paths.tsv.read_text(encoding="utf-8").splitlines()
    assert len(lines) == 2 and len(lines[1].split("\t")) == len(LOG_COLUMNS_V2)
    with pytest.raises(SessionError, match="without the column"):
        resumed.append(row | {"trial_index": 2, "score": 0.5})
    assert len(log.paths.tsv.read_text(encoding="utf-8").splitlines()) == 2


#: the sentences protocol cut to two sentences and two short tracks of three levels
SHORT = {
    r"      - \{id: s0[3-9], text: \S+\}\n": "",
    r"      - \{id: s10, text: \S+\}\n": "",
    r"      s0[3-9]: \[.*\]\n": "",
    r"      s10: \[.*\]\n": "",
    r"(?s)blocks:.*?presentation:": """blocks:
  - {id: audio, stimulus_set: sentences, task: sentence, sets: 1, presentations_per_condition: 1,
     conditions: [audio_p2, audio_m4, audio_m10], design: staircase,
     staircase: {rule: brand_kollmeier, start: audio_p2, trials: 2}}
  - {id: emphasized, stimulus_set: sentences, task: sentence, sets: 1,
     presentations_per_condition: 1, conditions: [emphasized_p2, emphasized_m4, emphasized_m10],
     design: staircase, staircase: {rule: brand_kollmeier, start: emphasized_p2, trials: 2}}

presentation:""",
}


@pytest.mark.slow
def test_a_typed_session_online_in_chromium_is_exported_and_scored(tmp_path) -> None:
    """The typed task served in headless Chromium: the answers typed into the field
    (Japanese text through the driver's key events), stored with their scores, the staircase
    moved by them on the server, exported as the lab's files."""
    from sqlalchemy import select
    from sqlalchemy.orm import Session

    from facelab.experiment.cli import main
    from facelab.experiment.online.db import Action
    from tests.task_protocols import one_online_session, short_task_protocol

    path = short_task_protocol("kato2021_srt_sentences", tmp_path, SHORT)
    server, rows = one_online_session(path, tmp_path)
    assert (tmp_path / "shots" / "typed.png").exists()
    with Session(server.engine) as db:
        typed = {a.record["trial_index"]: a.record["value"]
                 for a in db.scalars(select(Action)) if a.record.get("trial_index")}  # fmt: skip
    assert len(rows) == 4 == len(typed)
    for r in rows:
        assert (r["response"] or "") == typed[r["trial_index"]]
        assert r["screen"] == "typed" and 0.0 <= r["score"] <= 1.0
    out = tmp_path / "results"
    assert main(["export", "--db", f"sqlite:///{tmp_path / 'db.sqlite'}", "--results",
                 str(out), "--protocol", str(path)]) == 0  # fmt: skip
    log = pd.read_csv(next(out.rglob("*_beh.tsv")), sep="\t", keep_default_na=False)
    assert list(log["score"].astype(float)) == [r["score"] for r in sorted(
        rows, key=lambda r: r["trial_index"])]  # fmt: skip
    assert not math.isnan(float(log["score"].iloc[0]))


def test_review_cases_a_misheard_word_a_missing_mark_and_keywords_out_of_order(
    tmp_path,
) -> None:
    """From an independent review: a one-mora mishearing (白い heard as 黒い) is not a typo
    by default; control and zero-width characters are dropped and the log's missing mark is
    no answer; keywords must be said in the order listed; QUEST+ runs on typed answers."""
    protocol = _protocol()
    screen = _typed_screen(protocol, "s03")  # 白い 犬 庭 寝る
    assert screen.score("黒い犬が庭で寝る") == 0.75
    assert screen.score("白い犬が庭で寝る") == 1.0
    assert typed_text("赤い\u200b車\x00") == "赤い車"
    with pytest.raises(AnswerError, match="missing value"):
        screen.answer("sentence", {"text": " n/a "}, rt_s=1.0, timestamp="t")
    text = protocol_path("kato2021_srt_sentences").read_text(encoding="utf-8")
    swapped = text.replace("      s01: [赤い, 車, 止まった]", "      s01: [車, 赤い, 止まった]")
    assert "tasks[0].keywords.s01: keyword '赤い' is not said in '赤い車が止まった。' after" in (
        _problems(swapped, tmp_path))  # fmt: skip
    absent = text.replace("      s01: [赤い, 車, 止まった]", "      s01: [赤い, 犬, 止まった]")
    assert "keyword '犬' is not said" in _problems(absent, tmp_path)
    quest = text.replace("rule: brand_kollmeier, start: audio_p2, trials: 20, target_score: 0.5, "
                         "assumed_slope: 0.15", "rule: quest_plus, trials: 20")  # fmt: skip
    path = tmp_path / "quest.yaml"
    path.write_text(quest, encoding="utf-8")
    state = new_staircase(load_protocol_text(quest, path=path, base_dir=tmp_path), "audio")
    assert state.gamma == 0.0
