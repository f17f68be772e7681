"""Simulated participants -> session logs -> loading -> analysis -> figures and report."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from facelab.analysis.load import load_results
from facelab.errors import AnalysisError
from facelab.experiment.cli import main
from facelab.protocol import load_protocol
from facelab.sessionlog import LOG_COLUMNS
from tests.session_edits import rewrite_ratings, rewrite_rows


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("sim")
    kato = Path(__file__).resolve().parents[1] / "protocols" / "kato2021.yaml"
    assert (
        main(["simulate", str(kato), "--participants", "8", "--sim-seed", "3",
              "--results", str(root)])
        == 0
    )
    return root


def test_simulation_writes_complete_deterministic_sessions(
    simulated: Path, kato_path: Path, tmp_path: Path
) -> None:
    data = load_results(simulated)
    assert data["participant"].nunique() == 8
    assert data.groupby("participant").size().eq(36).all()  # 18 trials x 2 items
    assert data["simulated"].all() and data["rating"].between(0, 100).all()
    assert data["rating_start"].isna().all()  # marker hidden: no start value
    again = tmp_path / "again"
    assert (
        main(
            [
                "simulate",
                str(kato_path),
                "--participants",
                "8",
                "--sim-seed",
                "3",
                "--results",
                str(again),
            ]
        )
        == 0
    )
    for tsv in simulated.rglob("*_beh.tsv"):
        assert (again / tsv.relative_to(simulated)).read_bytes() == tsv.read_bytes()


def test_simulated_effects_follow_the_model(tmp_path: Path, kato_path: Path) -> None:
    assert (
        main(
            [
                "simulate",
                str(kato_path),
                "--participants",
                "40",
                "--sim-seed",
                "9",
                "--results",
                str(tmp_path),
                "--effect",
                "standard=30",
                "--effect",
                "emphasized=-20",
            ]
        )
        == 0
    )
    means = load_results(tmp_path).groupby("condition")["rating"].mean()
    assert means["standard"] - means["baseline"] == pytest.approx(30, abs=4)
    assert means["emphasized"] - means["baseline"] == pytest.approx(-20, abs=4)


def test_simulate_refuses_to_overwrite(
    simulated: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    before = {p: p.read_bytes() for p in simulated.rglob("*.tsv")}
    assert main(["simulate", str(kato_path), "--sim-seed", "4", "--results", str(simulated)]) == 2
    assert "already exist" in capsys.readouterr().err
    assert {p: p.read_bytes() for p in simulated.rglob("*.tsv")} == before
    assert (
        main(
            [
                "simulate",
                str(kato_path),
                "--sim-seed",
                "4",
                "--results",
                str(simulated),
                "--effect",
                "nope=3",
            ]
        )
        == 2
    )


def test_analyze_writes_tables_figures_and_report(
    simulated: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = simulated / "kato2021" / "analysis"
    assert main(["analyze", str(kato_path), str(simulated), "--force"]) == 0
    printed = capsys.readouterr().out
    assert "288 SIMULATED responses from 8 participants" in printed
    for name in (
        "rm_anova",
        "pairwise_paired",
        "friedman",
        "lmm_anova",
        "paper_anova",
        "paper_tukey",
        "paper_layout",
        "cell_means",
    ):
        assert (out / f"{name}.csv").stat().st_size > 0
    rm = pd.read_csv(out / "rm_anova.csv")
    assert len(rm) == 4 and set(rm.df2) == {14}  # 2 items x 2 sets, (3-1)(8-1)
    paper = pd.read_csv(out / "paper_anova.csv")
    assert sorted(paper.df2) == [45, 45, 93, 93]  # pooled ratings: the paper's df
    layout = pd.read_csv(out / "paper_layout.csv")
    assert set(layout.reported_anova_p) == {0.0221, 0.0068, 0.0045, 0.0053}
    cells = pd.read_csv(out / "cell_means.csv")
    data = load_results(simulated)
    assert len(cells) == data.groupby(["item", "stimulus_set", "participant", "condition"]).ngroups
    for stem in ("naturalness_vowels", "mouth_shape_sentences"):
        png = (out / f"fig_{stem}.png").read_bytes()
        assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000
        assert (out / f"fig_{stem}.svg").read_text().lstrip().startswith("<?xml")
    report = (out / "report.html").read_text()
    assert "SIMULATED DATA" in report and "0.0221" in report and "pseudo-replication" in report
    assert report.count("data:image/png;base64,") == 4
    assert "SIMULATED DATA" in (out / "report.md").read_text()


def test_figure_brackets_use_the_table_p_values(simulated: Path, kato_path: Path) -> None:
    from facelab.analysis.study import analyze_study, bracket_pairs

    data = load_results(simulated)
    res = analyze_study(data, load_protocol(kato_path), method="rm")
    br = bracket_pairs(res, item="mouth_shape", stimulus_set="sentences")
    pw = res.pairwise[
        (res.pairwise.item == "mouth_shape") & (res.pairwise.stimulus_set == "sentences")
    ]
    assert list(br.p) == list(pw.p_adj)
    res = analyze_study(data, load_protocol(kato_path), method="paper")
    br = bracket_pairs(res, item="mouth_shape", stimulus_set="sentences")
    tk = res.paper_tukey[
        (res.paper_tukey.item == "mouth_shape") & (res.paper_tukey.stimulus_set == "sentences")
    ]
    assert list(br.p) == list(tk.p_adj)


def _copy(simulated: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "r"
    shutil.copytree(simulated, dst)
    return dst


def _first_tsv(root: Path) -> Path:
    return sorted(root.rglob("*_beh.tsv"))[0]


def test_load_errors(simulated: Path, tmp_path: Path) -> None:
    root = _copy(simulated, tmp_path)
    tsv = _first_tsv(root)
    lines = tsv.read_text().splitlines(keepends=True)
    tsv.write_text("".join([*lines, lines[1]]))  # a rating twice
    with pytest.raises(AnalysisError, match="rating given twice"):
        load_results(root)
    tsv.write_text("".join([*lines, lines[1][:30]]))
    with pytest.raises(AnalysisError, match=r"cut off mid-write.*--resume"):
        load_results(root)
    # cut inside the last column (the protocol's digest): read as another protocol before
    tsv.write_text("".join([*lines, lines[1].rstrip("\n")[:-20]]))
    with pytest.raises(AnalysisError, match=r"cut off mid-write.*--resume"):
        load_results(root)
    fields = lines[1].split("\t")
    fields[LOG_COLUMNS.index("timestamp")] = "yesterday"
    tsv.write_text("".join([lines[0], "\t".join(fields), *lines[2:]]))
    with pytest.raises(AnalysisError, match=r"_beh.tsv:2: column 'timestamp' should be a date"):
        load_results(root)
    tsv.write_bytes("".join(lines).encode("utf-8") + b"kato2021\tP01\tvow\xe9ls\n")
    with pytest.raises(AnalysisError, match=rf"_beh.tsv:{len(lines) + 1}: not UTF-8 text"):
        load_results(root)
    fields = lines[1].split("\t")
    fields[11] = "130.0"
    tsv.write_text("".join([lines[0], "\t".join(fields), *lines[2:]]))
    with pytest.raises(AnalysisError, match=r"rating 130 .* outside the scale 0..100"):
        load_results(root)
    fields = lines[1].split("\t")
    fields[0] = "other"
    tsv.write_text("".join([lines[0], "\t".join(fields), *lines[2:]]))
    with pytest.raises(AnalysisError, match=r"_beh.tsv:2: study is 'other', but the file's name"):
        load_results(root)
    fields = lines[2].split("\t")
    fields[1] = "P02"  # a row pasted from another participant's log
    tsv.write_text("".join([lines[0], lines[1], "\t".join(fields), *lines[3:]]))
    with pytest.raises(AnalysisError, match=r"_beh.tsv:3: participant is 'P02', but"):
        load_results(root)
    fields[1] = "n/a"  # found by fuzzing: a statsmodels MissingDataError traceback
    tsv.write_text("".join([lines[0], lines[1], "\t".join(fields), *lines[3:]]))
    with pytest.raises(AnalysisError, match=r"_beh.tsv:3: column 'participant' is empty"):
        load_results(root)
    tsv.write_text("".join(lines))
    other = root / "sub-Q01" / "ses-1"
    other.mkdir(parents=True)
    moved = [line.replace("kato2021\tP01\t", "other\tQ01\t", 1) for line in lines]
    (other / "sub-Q01_ses-1_task-other_beh.tsv").write_text("".join(moved))
    with pytest.raises(AnalysisError, match="more than one study"):
        load_results(root)
    shutil.rmtree(root / "sub-Q01")
    tsv.write_text("".join([lines[0].replace("rating\t", "score\t"), *lines[1:]]))
    with pytest.raises(AnalysisError, match="unexpected header"):
        load_results(root)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(AnalysisError, match="no session logs"):
        load_results(empty)
    with pytest.raises(AnalysisError, match="results folder not found"):
        load_results(tmp_path / "nope")


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (("session", "one"), r'"session" is \'one\', expected a whole number >= 1'),
        (("session", 2), r"session is 2, but the log's name says 1"),
        (("participant", "P09"), r"participant is 'P09', but the log's name says 'P01'"),
        (("simulated", "yes"), r'"simulated" is \'yes\', expected true or false'),
    ],
)
def test_an_edited_session_file_is_refused_in_words(
    simulated: Path, tmp_path: Path, edit: tuple[str, object], message: str
) -> None:
    """A session file whose session was not a whole number was a ValueError traceback in
    the presentation table; one naming another participant was analysed."""
    import json

    root = _copy(simulated, tmp_path)
    (meta_path,) = _first_tsv(root).parent.glob("*_session.json")
    meta = json.loads(meta_path.read_text(encoding="utf-8"))
    meta[edit[0]] = edit[1]
    meta_path.write_text(json.dumps(meta), encoding="utf-8")
    with pytest.raises(AnalysisError, match=message):
        load_results(root)


def test_sessions_without_responses_are_named_not_dropped_silently(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A session folder whose response log is missing, or holds only its header, was left
    out of every table without a word."""
    root = _copy(simulated, tmp_path)
    first, second = sorted(root.rglob("*_beh.tsv"))[:2]
    first.unlink()
    second.write_text(second.read_text(encoding="utf-8").splitlines()[0] + "\n")
    other = first.parents[1].parent / "sub-P09" / "ses-1"  # a study named alike: not this one's
    other.mkdir(parents=True)
    (other / "sub-P09_ses-1_task-kato2021_v2_session.json").write_text("{}", encoding="utf-8")
    out = tmp_path / "analysis"
    assert main(["analyze", str(kato_path), str(root), "--out", str(out), "--bootstrap", "0"]) == 0
    said = capsys.readouterr().out
    for where, text in ((said, "stdout"), ((out / "report.md").read_text(encoding="utf-8"), "md")):
        assert "2 session(s) hold no response and are in no table" in where, text
        assert "P09" not in where, text
        assert "P01/1 (no response log beside its" in where and "P02/1 (its response log holds " \
            "only the header line)" in where, text


@pytest.mark.parametrize(
    ("column", "value", "message"),
    [
        (8, "other_condition", "condition is 'other_condition' but the participant's design has"),
        (4, "sentences", "block is 'sentences' but the participant's design has 'vowels'"),
        (6, "", "stimulus_set is '' but"),
        (3, "101", "trial 101: the design of P01 has 18 trials"),
        (9, "-1", "repetition is -1 but"),
        (17, "  ", "screen is '  ' but block 'vowels' shows 'vas'"),
    ],
)
def test_a_row_off_the_participants_design_is_refused(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys, column: int, value: str, message: str
) -> None:
    """Found by fuzzing the logs: a row edited to another condition, block, set or trial
    index was analysed (or silently dropped) as if the participant had seen it. The design
    is a pure function of the protocol and the participant id, so analyze checks each row
    against it."""
    root = _copy(simulated, tmp_path)
    tsv = _first_tsv(root)
    lines = tsv.read_text().splitlines(keepends=True)
    fields = lines[1].split("\t")
    if column == 8:  # another condition of the protocol, not the one of this trial
        value = next(c for c in ("baseline", "standard", "emphasized") if c != fields[8])
        message = message.replace("other_condition", value)
    fields[column] = value
    tsv.write_text("".join([lines[0], "\t".join(fields), *lines[2:]]))
    assert main(["analyze", str(kato_path), str(root), "--force"]) == 2
    err = capsys.readouterr().err
    assert message in err, err
    assert "participant P01 " in err


@pytest.mark.slow
def test_incomplete_participant_is_reported_and_left_out_of_the_rm_analysis(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _copy(simulated, tmp_path)
    tsv = sorted(root.rglob("sub-P05*_beh.tsv"))[0]
    lines = tsv.read_text().splitlines(keepends=True)
    keep = [line for line in lines if "\tsentences\tpassage\tbaseline\t" not in line]
    tsv.write_text("".join(keep))
    assert main(["analyze", str(kato_path), str(root), "--force"]) == 0
    out = capsys.readouterr().out
    assert "incomplete session(s): P05/1 (32 of 36)" in out
    assert "sentences: participant(s) P05 lack a condition; left out" in out
    layout = pd.read_csv(root / "kato2021" / "analysis" / "paper_layout.csv")
    rm = layout[(layout.procedure == "rm") & (layout.stimulus_set == "sentences")]
    assert set(rm.n_participants) == {7} and set(rm.df2) == {12}
    report = (root / "kato2021" / "analysis" / "report.md").read_text()
    assert "## Data checks" in report and "P05/1 (32 of 36)" in report
    assert main(["analyze", str(kato_path), str(root), "--force", "--exclude", "P05"]) == 0
    assert "from 7 participants" in capsys.readouterr().out


def test_simulated_is_on_every_row_even_without_the_session_file(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _copy(simulated, tmp_path)
    for sidecar in root.rglob("*_session.json"):
        sidecar.unlink()
    data = load_results(root, study="kato2021")
    assert data["simulated"].eq(True).all()
    assert main(["analyze", str(kato_path), str(root), "--force"]) == 0
    assert "SIMULATED responses" in capsys.readouterr().out
    report = (root / "kato2021" / "analysis" / "report.md").read_text()
    assert "SIMULATED DATA" in report


def test_mixed_data_are_labelled_mixed(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _copy(simulated, tmp_path)
    tsv = sorted(root.rglob("sub-P03*_beh.tsv"))[0]
    tsv.write_text(tsv.read_text().replace("\ttrue\t", "\tfalse\t"))  # as if a person rated
    assert main(["analyze", str(kato_path), str(root), "--force"]) == 0
    out = capsys.readouterr().out
    assert "MIXED (simulated and real) responses" in out and "7 of 8 sessions" in out
    assert "MIXED DATA" in (root / "kato2021" / "analysis" / "report.md").read_text()


def test_analyze_checks_the_protocol_the_sessions_ran(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _copy(simulated, tmp_path)
    changed = tmp_path / "changed.yaml"
    changed.write_text(
        kato_path.read_text(encoding="utf-8").replace("アバターの口の形", "アバターの目の形"),
        encoding="utf-8",
    )
    assert main(["analyze", str(changed), str(root), "--force"]) == 2
    err = capsys.readouterr().err
    assert "8 session(s) ran a different version of the protocol file" in err
    assert "--accept-protocol-change" in err
    code = main(["analyze", str(changed), str(root), "--force", "--accept-protocol-change"])
    assert code == 0
    assert "analysed anyway" in capsys.readouterr().out


def test_a_condition_nobody_saw_is_reported_not_a_crash(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    root = _copy(simulated, tmp_path)
    for tsv in root.rglob("*_beh.tsv"):
        lines = tsv.read_text().splitlines(keepends=True)
        tsv.write_text("".join(x for x in lines if "\temphasized\t" not in x))
    assert main(["analyze", str(kato_path), str(root), "--force"]) == 0
    out = capsys.readouterr().out
    assert "no responses for condition(s) emphasized: left out of every analysis" in out
    assert "F(1,7)" in out  # two conditions: df 1 and 7


@pytest.mark.parametrize("n", [1, 2])
def test_a_pilot_of_one_or_two_participants_is_analysed(
    n: int, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 34.1: descriptive tables and figures for any n; an inferential row that the data
    cannot give is marked not estimable with the reason, not an error that blames the data."""
    argv = ["simulate", str(kato_path), "--participants", str(n), "--sim-seed", "1"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    out = tmp_path / "analysis"
    assert main(["analyze", str(kato_path), str(tmp_path), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    layout = pd.read_csv(out / "paper_layout.csv")
    assert len(layout) == 8  # 2 items x 2 sets x (rm, paper)
    rm = layout[layout["procedure"] == "rm"]
    if n == 1:
        assert rm["f"].isna().all()
        assert rm["pairs_p_lt_05"].str.startswith("not estimable: 1 participant").all()
        assert "not estimable" in printed
    else:
        assert rm["f"].notna().all() and (rm["n_participants"] == 2).all()
    paper = layout[layout["procedure"] == "paper"]
    assert paper["f"].notna().all()  # the pooled procedure needs repeated ratings only
    if n == 1:  # ... and says whose they are
        assert "the paper's procedure has one participant's ratings" in printed
        for name in ("rm_anova", "pairwise_paired", "friedman", "lmm_anova"):  # say why empty
            table = pd.read_csv(out / f"{name}.csv")
            assert len(table) == 4 and list(table.columns) == ["item", "stimulus_set", "note"]
            assert table["note"].str.startswith("not estimable: 1 participant(s)").all()
    cells = pd.read_csv(out / "cell_means.csv")
    assert len(cells) == 2 * 2 * 3 * n and cells["mean"].notna().all()
    report = (out / "report.html").read_text(encoding="utf-8")
    assert report.count("data:image/png;base64,") == 4
    if n == 1:
        assert "not estimable" in report and "nan (nan" not in report


def test_dropped_frames_are_tabled_and_trials_over_a_threshold_excluded(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Issue 34.3: the analysis reads clip_frames_dropped - per condition always, and with
    --max-dropped-frames leaves out the responses of trials over it, saying so."""
    argv = ["simulate", str(kato_path), "--participants", "3", "--sim-seed", "2"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    tsv = next(tmp_path.rglob("sub-P01/ses-1/*_beh.tsv"))
    lines = tsv.read_text(encoding="utf-8").splitlines()
    head = lines[0].split("\t")
    col, trial = head.index("clip_frames_dropped"), head.index("trial_index")
    drops = {"1": "23", "2": "3", "5": "9"}  # frames dropped by trial (both items of a trial)
    edited = [lines[0]]
    for line in lines[1:]:
        cells = line.split("\t")
        cells[col] = drops.get(cells[trial], cells[col])
        edited.append("\t".join(cells))
    tsv.write_text("\n".join(edited) + "\n", encoding="utf-8")
    conditions = {ln.split("\t")[trial]: ln.split("\t")[head.index("condition")]
                  for ln in lines[1:]}  # fmt: skip

    out = tmp_path / "all"
    assert main(["analyze", str(kato_path), str(tmp_path), "--out", str(out)]) == 0
    quality = pd.read_csv(out / "presentation_quality.csv")
    assert quality["frames_dropped"].sum() == 23 + 3 + 9
    assert quality["trials_with_drops"].sum() == 3 and quality["excluded_trials"].sum() == 0
    assert quality["max_dropped"].max() == 23

    out = tmp_path / "cut"
    capsys.readouterr()
    argv = ["analyze", str(kato_path), str(tmp_path), "--out", str(out), "--max-dropped-frames"]
    assert main([*argv, "5"]) == 0
    printed = capsys.readouterr().out
    assert "excluded 4 responses of 2 trials whose clip dropped more than 5 frames" in printed
    quality = pd.read_csv(out / "presentation_quality.csv").set_index(["stimulus_set", "condition"])
    assert quality["excluded_trials"].sum() == 2
    for t in ("1", "5"):
        assert quality.xs(conditions[t], level="condition")["excluded_trials"].sum() >= 1
    ratings = pd.read_csv(out / "ratings.csv")
    p01 = ratings[ratings["participant"] == "P01"]
    assert not set(p01["trial_index"].astype(str)) & {"1", "5"} and len(ratings) == 3 * 36 - 4
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "--max-dropped-frames" in report and "frames the clips dropped" in report


def test_the_pilot_summary_names_sessions_and_an_item_everyone_answers_alike(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["simulate", str(kato_path), "--participants", "2", "--sim-seed", "5"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    for sset in ("vowels", "sentences"):
        rewrite_ratings(tmp_path, item="naturalness", stimulus_set=sset, rating=lambda r: 50)
    dest = tmp_path / "analysis"
    assert main(["analyze", str(kato_path), str(tmp_path), "--out", str(dest)]) == 0
    assert "naturalness / sentences: every one of 12 ratings is 50" in capsys.readouterr().out
    sessions = pd.read_csv(dest / "pilot_sessions.csv")
    assert list(sessions["participant"]) == ["P01", "P02"]
    assert (sessions["responses"] == sessions["expected"]).all()
    assert (sessions["minutes"] > 0).all() and (sessions["median_rt_s"] > 0).all()
    items = pd.read_csv(dest / "pilot_items.csv").set_index(["item", "stimulus_set"])
    assert items.loc[("naturalness", "vowels"), "all_the_same"]
    assert not items.loc[("mouth_shape", "vowels"), "all_the_same"]


def test_a_study_of_one_condition_is_described_not_compared(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pilot of one method: its ratings are tabled and drawn; every comparison is marked not
    estimable with the reason (it used to fail, saying no rating matched the protocol)."""
    from tests.protocol_edits import ONE_CONDITION

    path = tmp_path / "one.yaml"
    path.write_text(ONE_CONDITION, encoding="utf-8")
    argv = ["simulate", str(path), "--participants", "3", "--sim-seed", "4"]
    assert main([*argv, "--results", str(tmp_path / "res")]) == 0
    out = tmp_path / "analysis"
    assert main(["analyze", str(path), str(tmp_path / "res"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "ratings for one condition only, nothing to compare" in printed
    assert "responses for 1 condition" not in printed  # not also "not analysed"
    cells = pd.read_csv(out / "cell_means.csv")
    assert len(cells) == 3 and set(cells["condition"]) == {"standard"}
    assert cells["mean"].notna().all()
    layout = pd.read_csv(out / "paper_layout.csv")
    assert len(layout) == 2 and layout["f"].isna().all()
    assert (out / "fig_naturalness_short.png").stat().st_size > 5_000


def test_who_is_analysed_is_said_excluded_and_repeat_sessions_alike(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--exclude is named in the report (not only in the command line that ran it); a
    participant's second session is named as pooled with the first; excluding everyone is
    refused in words, not a traceback."""
    root = _copy(simulated, tmp_path)
    first = next(root.rglob("sub-P01/ses-1"))
    second = first.with_name("ses-2")
    second.mkdir()
    for f in first.iterdir():  # the same participant again, as session 2
        (second / f.name.replace("ses-1", "ses-2")).write_bytes(f.read_bytes())
    assert rewrite_rows(second, lambda row: bool(row.update(session="2")) or True) > 0
    (session,) = second.glob("*_session.json")
    session.write_text(session.read_text(encoding="utf-8").replace('"session": 1',
                                                                   '"session": 2'))  # fmt: skip
    out = tmp_path / "a"
    assert main(["analyze", str(kato_path), str(root), "--out", str(out), "--exclude",
                 "P03"]) == 0  # fmt: skip
    printed = capsys.readouterr().out
    report = (out / "report.md").read_text(encoding="utf-8")
    for text in (printed, report):
        assert "left out by --exclude: P03" in text
        assert "1 participant(s) ran more than one session (P01: sessions 1, 2)" in text
    everyone = [a for i in range(1, 9) for a in ("--exclude", f"P{i:02d}")]
    assert main(["analyze", str(kato_path), str(root), "--out", str(tmp_path / "b"),
                 *everyone]) == 2  # fmt: skip
    err = capsys.readouterr().err
    assert "--exclude leaves no participant" in err and "Traceback" not in err
    assert not (tmp_path / "b").exists()


def test_one_participant_of_a_graded_study_is_described(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A one-person pilot of a graded (levels) VAS study is analysed: descriptive tables, the
    trend contrast named not estimable (it was refused with no output at all)."""
    path = Path(__file__).resolve().parents[1] / "protocols" / "horii_impression.yaml"
    argv = ["simulate", str(path), "--participants", "1", "--sim-seed", "5"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    out = tmp_path / "a"
    assert main(["analyze", str(path), str(tmp_path), "--out", str(out), "--bootstrap",
                 "0"]) == 0  # fmt: skip
    assert "the trend contrast over the levels is not estimable" in capsys.readouterr().out
    assert (out / "cell_means.csv").is_file() and not (out / "trend_contrast.csv").exists()


def test_a_participant_who_never_moved_the_scale_or_answers_below_chance_is_named(
    simulated: Path, tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ratings all at one value (the scale left where it started) and forced choices right
    less often than guessing (reversed keys) are named in the notes, not analysed silently
    as answers; healthy simulated participants are not named."""
    from facelab.analysis.pilot import below_chance

    root = _copy(simulated, tmp_path)
    changed = rewrite_rows(root, lambda row: row["participant"] == "P02"
                           and bool(row.update(rating="50")) is False)  # fmt: skip
    assert changed == 36
    assert main(["analyze", str(kato_path), str(root), "--out", str(tmp_path / "a")]) == 0
    printed = capsys.readouterr().out
    assert printed.count("rated") == 2 and "participant P02 rated naturalness 50 on every " \
        "one of 18 trials" in printed and "participant P02 rated mouth_shape 50" in printed
    y = np.r_[np.zeros(14), np.ones(6)]  # 6 of 20 at a 2AFC: p = 0.058, not named
    trials = pd.DataFrame({"participant": "P01", "y": y})
    assert below_chance(trials, task="t", chance=0.5) == []
    notes = below_chance(trials.assign(y=np.r_[np.zeros(17), np.ones(3)]), task="t", chance=0.5)
    assert len(notes) == 1 and "right on 3 of 20 trials, below guessing (50%" in notes[0]
