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
