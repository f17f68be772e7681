"""analysis.stats against R reference values (tests/reference/stats_reference.R), rtol 1e-6."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from facelab.analysis import stats
from facelab.errors import AnalysisError

REF_DIR = Path(__file__).parent / "reference"
REF = json.loads((REF_DIR / "stats_reference.json").read_text())
RTOL = 1e-6


def close(actual: float, expected: float) -> None:
    """Equal to 1e-6 relative, or 1e-9 absolute: R's ptukey has about 1e-12 absolute accuracy,
    so tiny Tukey p-values (e.g. 3.07e-8 in chickwts) differ relatively (statistics.md §0)."""
    assert actual == pytest.approx(expected, rel=RTOL, abs=1e-9)


def _between(name: str, dv: str, group: str) -> pd.DataFrame:
    data = pd.read_csv(REF_DIR / f"{name}.csv")
    # R's factor levels: the first level is the 'b' side of the first pairs ("trt1-ctrl")
    first = REF[name]["tukey"][0]["pair"].split("-")[1]
    rest = [
        row["pair"].split("-")[0] for row in REF[name]["tukey"] if row["pair"].endswith(f"-{first}")
    ]
    data[group] = pd.Categorical(data[group], categories=[first, *rest])
    return data


@pytest.mark.parametrize(
    ("name", "dv", "group"), [("plantgrowth", "weight", "group"), ("chickwts", "weight", "feed")]
)
def test_one_way_anova_and_tukey_match_r(name: str, dv: str, group: str) -> None:
    data = _between(name, dv, group)
    anova = stats.one_way_anova(data, dv=dv, between=group)
    assert list(anova.columns) == ["df1", "df2", "f", "p", "eta_sq"]
    for key, value in REF[name]["anova"].items():
        close(anova[key][0], value)
    tukey = stats.tukey_hsd(data, dv=dv, between=group)
    assert list(tukey.columns) == ["a", "b", "diff", "ci_low", "ci_high", "p_adj"]
    expected = {row["pair"]: row for row in REF[name]["tukey"]}
    assert len(tukey) == len(expected)
    for row in tukey.itertuples():
        ref = expected[f"{row.b}-{row.a}"]  # R names pairs "b-a" with diff = mean(b) - mean(a)
        for key in ("diff", "ci_low", "ci_high", "p_adj"):
            close(getattr(row, key), ref[key])


def test_chickwts_is_unbalanced() -> None:  # so the test above exercises Tukey-Kramer
    sizes = pd.read_csv(REF_DIR / "chickwts.csv").groupby("feed").size()
    assert sizes.nunique() > 1


@pytest.mark.parametrize("name", ["rm3", "rm4"])
def test_within_subject_procedures_match_r(name: str) -> None:
    data = pd.read_csv(REF_DIR / f"{name}.csv")
    kw = {"dv": "rating", "within": "condition", "subject": "participant"}
    rm = stats.rm_anova(data, **kw)
    assert list(rm.columns) == [
        "df1",
        "df2",
        "f",
        "p",
        "w_mauchly",
        "p_mauchly",
        "eps_gg",
        "p_gg",
        "eps_hf",
        "p_hf",
        "eta_g_sq",
        "eta_p_sq",
    ]
    for key, value in REF[name]["rm_anova"].items():
        close(rm[key][0], value)
    assert rm["eps_gg"][0] < 0.7  # the fixtures violate sphericity, so corrections matter
    fr = stats.friedman(data, **kw)
    for key, value in REF[name]["friedman"].items():
        close(fr[key][0], value)
    for method in ("holm", "bonferroni", "none"):
        pw = stats.pairwise_paired(data, **kw, padjust=method)
        assert list(pw.columns) == ["a", "b", "t", "df", "p_unc", "p_adj", "d_z"]
        for row, ref in zip(pw.itertuples(), REF[name]["pairwise"], strict=True):
            assert (row.a, row.b) == (ref["a"], ref["b"])
            for key in ("t", "df", "p_unc", "d_z"):
                close(getattr(row, key), ref[key])
            close(row.p_adj, ref["p_unc"] if method == "none" else ref[f"p_{method}"])


def test_repeated_ratings_are_averaged_before_rm_anova() -> None:
    data = pd.read_csv(REF_DIR / "rm3.csv")
    means = data.groupby(["participant", "condition"], as_index=False, sort=False)["rating"].mean()
    kw = {"dv": "rating", "within": "condition", "subject": "participant"}
    pd.testing.assert_frame_equal(stats.rm_anova(data, **kw), stats.rm_anova(means, **kw))


def test_mixed_model_equals_aggregated_rm_anova_and_lme4() -> None:
    data = pd.read_csv(REF_DIR / "rm3.csv")
    kw = {"dv": "rating", "within": "condition", "subject": "participant"}
    lmm = stats.lmm_anova(data, **kw)
    rm = stats.rm_anova(data, **kw)
    assert list(lmm.columns) == ["df1", "df2", "f", "p"]
    assert (lmm.df1[0], lmm.df2[0]) == (rm.df1[0], rm.df2[0])
    close(lmm.f[0], rm.f[0])
    close(lmm.p[0], rm.p[0])
    close(lmm.f[0], REF["rm3"]["lmer_f"])  # lme4's F for the same model


def test_lmm_uses_incomplete_data_where_rm_anova_refuses() -> None:
    data = pd.read_csv(REF_DIR / "rm3.csv")
    data = data[~((data.participant == "P03") & (data.condition == "standard"))]
    kw = {"dv": "rating", "within": "condition", "subject": "participant"}
    with pytest.raises(AnalysisError, match=r"missing cell\(s\).*P03 x standard"):
        stats.rm_anova(data, **kw)
    assert 0 < stats.lmm_anova(data, **kw).p[0] < 1


def test_p_adjust_matches_r_examples() -> None:
    p = [0.01, 0.04, 0.03, 0.2]
    # R: p.adjust(c(.01,.04,.03,.2), "holm") -> 0.04 0.09 0.09 0.20
    np.testing.assert_allclose(stats.p_adjust(p, method="holm"), [0.04, 0.09, 0.09, 0.2])
    np.testing.assert_allclose(stats.p_adjust(p, method="bonferroni"), [0.04, 0.16, 0.12, 0.8])
    with pytest.raises(AnalysisError, match="unknown p-value adjustment"):
        stats.p_adjust(p, method="fdr")


@pytest.mark.parametrize(
    ("frame", "kwargs", "message"),
    [
        (pd.DataFrame({"x": [1, 2]}), {"dv": "y", "between": "g"}, "missing column"),
        (
            pd.DataFrame({"y": [1.0, 2.0, 3.0], "g": ["a", "a", "a"]}),
            {"dv": "y", "between": "g"},
            "at least 2 levels",
        ),
        (
            pd.DataFrame({"y": ["1", "x", "3", "4"], "g": ["a", "a", "b", "b"]}),
            {"dv": "y", "between": "g"},
            "non-numeric",
        ),
        (
            pd.DataFrame({"y": [1.0, None, 3.0, 4.0], "g": ["a", "a", "b", "b"]}),
            {"dv": "y", "between": "g"},
            "missing value",
        ),
        (
            pd.DataFrame({"y": [1.0, 2.0, 3.0], "g": ["a", "b", "b"]}),
            {"dv": "y", "between": "g"},
            "fewer than 2 values",
        ),
    ],
)
def test_bad_input_gives_clear_errors(frame: pd.DataFrame, kwargs: dict, message: str) -> None:
    with pytest.raises(AnalysisError, match=message):
        stats.one_way_anova(frame, **kwargs)


def test_friedman_needs_three_levels() -> None:
    data = pd.read_csv(REF_DIR / "rm3.csv")
    two = data[data.condition != "emphasized"]
    with pytest.raises(AnalysisError, match="at least 3 levels"):
        stats.friedman(two, dv="rating", within="condition", subject="participant")
    rm = stats.rm_anova(two, dv="rating", within="condition", subject="participant")
    assert rm.w_mauchly[0] == 1.0 and rm.eps_gg[0] == 1.0  # sphericity is trivial with 2 levels


def test_covariates_constant_within_a_condition_are_kept_and_named() -> None:
    from facelab.analysis.stats import screen_covariates

    data = pd.DataFrame(
        {
            "condition": ["a"] * 4 + ["b"] * 4,
            "n_posture": [0, 0, 0, 0, 1, 2, 2, 3],  # none in the gesture-only condition
            "n_tag": [0, 0, 0, 0, 1, 1, 1, 1],  # marks the condition only
            "n_blink": [3, 4, 3, 5, 4, 3, 5, 4],
        }
    )
    used, notes = screen_covariates(data, ["n_posture", "n_tag", "n_blink"], condition="condition")
    assert used == ["n_posture", "n_blink"]
    assert notes == ["n_posture constant within a (0)", "n_tag fixed by condition"]


def test_two_participants_give_no_huynh_feldt_epsilon_and_ranks_need_differences() -> None:
    """At n = 2 the Huynh-Feldt estimate is 0/0 (eps_gg = 1/p exactly): NaN, not the -1 that
    rounding made of it; Friedman refuses means tied in every row and gives the exact
    chi2 = n (k - 1) to a perfectly consistent order, where the F of the RM ANOVA is
    undefined."""
    data = pd.read_csv(REF_DIR / "rm3.csv")
    two = data[data.participant.isin(sorted(data.participant.unique())[:2])]
    rm = stats.rm_anova(two, dv="rating", within="condition", subject="participant")
    assert np.isnan(rm.eps_hf[0]) and np.isnan(rm.p_hf[0]) and 0.5 <= rm.eps_gg[0] <= 1.0
    order = {"baseline": 30.0, "standard": 50.0, "emphasized": 70.0}
    perfect = data.assign(rating=data.condition.map(order) + data.participant.astype("category")
                          .cat.codes)  # fmt: skip
    fr = stats.friedman(perfect, dv="rating", within="condition", subject="participant")
    n = perfect.participant.nunique()
    assert fr.chi2[0] == pytest.approx(2 * n) and fr.kendall_w[0] == pytest.approx(1.0)
    with pytest.raises(AnalysisError, match="no residual variance"):
        stats.rm_anova(perfect, dv="rating", within="condition", subject="participant")
    with pytest.raises(AnalysisError, match="tied across the conditions"):
        stats.friedman(data.assign(rating=5.0), dv="rating", within="condition",
                       subject="participant")  # fmt: skip


def test_a_note_on_one_measure_leaves_the_others_compared() -> None:
    """A window whose width interval is open still has a determined PSS: with ``concerns``
    it stays in the PSS summary and tests and leaves only the width's; a series that too
    few participants determined is left out of the tests, not every comparison with it."""
    rng = np.random.default_rng(7)
    rows = [{"participant": f"P{i}", "condition": c, "pss_ms": 40 + 10 * j + rng.normal(0, 5),
             "width_ms": 150 + rng.normal(0, 10), "note": ""}
            for i in range(5) for j, c in enumerate(("a", "b", "c"))]  # fmt: skip
    table = pd.DataFrame(rows)
    table.loc[0, "note"] = "the width interval reaches beyond the widths searched"
    for i in range(3):  # series c: only two participants determined
        table.loc[3 * i + 2, "note"] = "the PSS ends on its search bound"
    concerns = {"pss_ms": "the PSS", "width_ms": "the width"}
    summary, tests = stats.series_comparison(table, measures=("pss_ms", "width_ms"),
                                             concerns=concerns)  # fmt: skip
    s = summary.set_index("condition")
    assert s.loc["a", "determined"] == 4 and not np.isnan(s.loc["a", "pss_ms_mean"])
    pss = tests[tests["measure"] == "pss_ms"]
    assert {(r.a, r.b) for r in pss.itertuples()} == {("all", "all"), ("a", "b")}
    assert set(pss["participants"]) == {5}  # P0's open width does not take its PSS away
    width = tests[tests["measure"] == "width_ms"]
    assert set(width["participants"]) == {4} and "c" in set(width["b"])  # P0 left out
    # without concerns any note leaves the row out of both measures
    _, plain = stats.series_comparison(table, measures=("pss_ms", "width_ms"))
    assert set(plain[plain["measure"] == "pss_ms"]["participants"]) == {4}
