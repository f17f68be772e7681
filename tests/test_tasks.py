"""Forced choice, identification, constant stimuli and staircases: protocol, design, timeline,
simulation, analyses (against R), and the shipped example protocols end to end."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from facelab.analysis import graded, identification, psychometric, stats
from facelab.analysis.load import load_results
from facelab.analysis.tasks import analyze_tasks
from facelab.design import PENDING, build_trials, trials_frame
from facelab.errors import AnalysisError, ProtocolError, SessionError
from facelab.experiment.adaptive import Staircases
from facelab.experiment.cli import main
from facelab.experiment.simulate import simulate_study
from facelab.experiment.timeline import ChoiceAnswer, ChoiceScreen, compile_timeline, trial_screens
from facelab.protocol import load_protocol
from facelab.resources import protocol_path
from facelab.sessionlog import SessionContext
from facelab.staircase import UpDownStaircase, convergence_probability, new_staircase

REF = Path(__file__).parent / "reference"
EXAMPLES = (
    "gain_2afc",
    "gain_staircase",
    pytest.param("gain_questplus", marks=pytest.mark.slow),  # ~13 s
    "method_identify",
    "gain_vas",
    "horii_impression_side",
)


# --------------------------------------------------------------------------- analyses vs R


@pytest.mark.parametrize(
    ("case", "data", "kwargs"),
    [
        ("afc_logistic_lapse0", "psychometric_2afc.csv", {"gamma": 0.5, "lapse_bounds": (0, 0)}),
        ("afc_logistic_lapse", "psychometric_2afc.csv", {"gamma": 0.5}),
        (
            "afc_weibull_lapse0",
            "psychometric_2afc.csv",
            {"gamma": 0.5, "lapse_bounds": (0, 0), "sigmoid": "weibull"},
        ),
        ("yesno_logistic_lapse0", "psychometric_yesno.csv", {"gamma": 0.0, "lapse_bounds": (0, 0)}),
    ],
)
def test_psychometric_fit_matches_r(case, data, kwargs):
    ref = json.loads((REF / "psychometric_R.json").read_text())[case]
    fit = psychometric.fit_psychometric(pd.read_csv(REF / data), **kwargs)
    assert fit.alpha == pytest.approx(ref["alpha"], rel=1e-4)
    assert fit.beta == pytest.approx(ref["beta"], rel=1e-3)
    assert fit.deviance == pytest.approx(ref["deviance"], rel=1e-4, abs=1e-6)
    if "lapse" in ref:
        assert fit.lapse == pytest.approx(ref["lapse"], rel=1e-3)
    if "loglik" in ref:
        assert fit.log_likelihood == pytest.approx(ref["loglik"], rel=1e-6)


def test_graded_trend_and_mixed_model_match_r():
    ref = json.loads((REF / "graded_R.json").read_text())
    data = pd.read_csv(REF / "graded.csv")
    trend = graded.trend_contrast(data).iloc[0]
    for key in ("slope", "se", "t", "p"):
        assert trend[key] == pytest.approx(ref["trend"][key], rel=1e-6)
    assert trend["df"] == ref["trend"]["df"]
    lmm = graded.graded_lmm(data).iloc[0]
    assert lmm["converged"]
    for key in ("intercept", "slope"):
        assert lmm[key] == pytest.approx(ref["lmm"][key], rel=1e-5)
    for key in ("slope_se", "sd_intercept", "sd_slope", "sd_residual"):
        assert lmm[key] == pytest.approx(ref["lmm"][key], rel=2e-3)
    assert lmm["corr"] == pytest.approx(ref["lmm"]["corr"], abs=2e-3)
    assert lmm["df"] == pytest.approx(ref["lmm"]["slope_df"], abs=1e-3)  # lmerTest
    assert lmm["p"] == pytest.approx(ref["lmm"]["slope_p"], rel=2e-3)


def test_confusion_accuracy_and_kappa_against_sklearn():
    metrics = pytest.importorskip("sklearn.metrics")
    rng = np.random.default_rng(5)
    labels = ["joy", "anger", "fear", "neutral"]
    target = rng.choice(labels, size=400)
    response = np.where(rng.random(400) < 0.6, target, rng.choice(labels, size=400))
    trials = pd.DataFrame({"participant": "P01", "target": target, "response": response})
    summary, recall = identification.identification_summary(trials, labels=labels)
    pooled = summary[summary["participant"] == "pooled"].iloc[0]
    assert pooled["kappa"] == pytest.approx(metrics.cohen_kappa_score(target, response))
    assert pooled["accuracy"] == pytest.approx(np.mean(target == response))
    # relative information transfer: sklearn's mutual information (nats) over the entropy of
    # what was portrayed (scipy, nats)
    from scipy.stats import entropy

    h_x = entropy(pd.Series(target).value_counts().to_numpy())
    rit = metrics.mutual_info_score(target, response) / h_x
    assert pooled["information_transfer"] == pytest.approx(rit, rel=1e-9)
    assert 0 < rit < 1
    expected = metrics.recall_score(target, response, labels=labels, average=None)
    got = recall[recall["participant"] == "pooled"].set_index("label").loc[labels, "recall"]
    np.testing.assert_allclose(got.to_numpy(), expected)
    matrix = identification.confusion_matrix(trials, labels=labels)
    np.testing.assert_array_equal(
        matrix.to_numpy(), metrics.confusion_matrix(target, response, labels=labels)
    )


def test_condition_model_matches_geepack():
    ref = json.loads((REF / "identification_R.json").read_text())
    data = pd.read_csv(REF / "identification.csv")
    order = ["none", "gestures_only", "composite"]
    for key, covariates in (("condition", ()), ("covariate", ("n_gesture",))):
        got = identification.correct_model(data, covariates=covariates, conditions=order)
        got = got.set_index("term")
        for r_term, values in ref[key]["terms"].items():
            term = {"(Intercept)": "Intercept", "n_gesture": "n_gesture"}.get(
                r_term, f"C(condition)[T.{r_term.removeprefix('condition')}]"
            )
            assert got.loc[term, "estimate"] == pytest.approx(values["estimate"], rel=1e-6)
            assert got.loc[term, "se_robust"] == pytest.approx(values["se"], rel=1e-6)
        assert got["correlation"].iloc[0] == pytest.approx(ref[key]["correlation"], rel=1e-6)
        # the bias-corrected SEs, by the formulas of Kauermann & Carroll (2001) and Mancl &
        # DeRouen (2001) written out here (unwhitened, scipy's matrix power)
        x = np.column_stack(
            [np.ones(len(data))]
            + [(data["condition"] == c).to_numpy(float) for c in order[1:]]
            + [data[c].to_numpy(float) for c in covariates]
        )
        args = (x, data["correct"].to_numpy(float), data["participant"].to_numpy())
        kw = {"beta": got["estimate"].to_numpy(), "rho": got["correlation"].iloc[0]}
        np.testing.assert_allclose(
            got["se"], _bias_corrected_se(*args, **kw, power=-0.5), rtol=1e-6
        )
        np.testing.assert_allclose(
            got["se_md"], _bias_corrected_se(*args, **kw, power=-1), rtol=1e-6
        )
        np.testing.assert_allclose(
            got["se_robust"], _bias_corrected_se(*args, **kw, power=0), rtol=1e-6
        )
        # each correction widens, Mancl-DeRouen more
        assert (got["se_robust"] < got["se"]).all() and (got["se"] < got["se_md"]).all()
        assert (got["df"] == 18 - len(got)).all()
        composite = got.loc["C(condition)[T.composite]"]
        assert composite["odds_ratio"] == pytest.approx(np.exp(composite["estimate"]))
        assert composite["or_ci_low"] < composite["odds_ratio"] < composite["or_ci_high"]
        assert got["note"].iloc[0].startswith("reference: none")


def _bias_corrected_se(
    x: np.ndarray,
    y: np.ndarray,
    cluster: np.ndarray,
    *,
    beta: np.ndarray,
    rho: float,
    power: float,
) -> np.ndarray:
    """SEs of a logistic GEE with exchangeable correlation ``rho`` at ``beta``:
    B^-1 (sum_i D_i' V_i^-1 (I - H_i)^p r_i r_i' (I - H_i)^p' V_i^-1 D_i) B^-1, with
    D_i = A_i X_i, V_i = A_i^1/2 R A_i^1/2, A_i = diag(mu (1 - mu)), H_i = D_i B^-1 D_i' V_i^-1,
    B = sum_i D_i' V_i^-1 D_i; p = -1/2 Kauermann-Carroll, -1 Mancl-DeRouen, 0 plain."""
    from scipy.linalg import fractional_matrix_power

    parts = []
    for c in dict.fromkeys(cluster):
        xi, yi = x[cluster == c], y[cluster == c]
        mu = 1 / (1 + np.exp(-xi @ beta))
        a = mu * (1 - mu)
        r_mat = np.full((len(yi), len(yi)), rho) + (1 - rho) * np.eye(len(yi))
        v = np.sqrt(a)[:, None] * r_mat * np.sqrt(a)[None, :]
        d = a[:, None] * xi
        parts.append((d, np.linalg.inv(v), yi - mu))
    b_inv = np.linalg.inv(sum(d.T @ vi @ d for d, vi, _ in parts))
    meat = 0
    for d, vi, r in parts:
        h = d @ b_inv @ d.T @ vi
        u = d.T @ vi @ np.real(fractional_matrix_power(np.eye(len(r)) - h, power)) @ r
        meat = meat + np.outer(u, u)
    return np.sqrt(np.diag(b_inv @ meat @ b_inv))


def test_condition_model_refuses_what_it_cannot_fit():
    data = pd.read_csv(REF / "identification.csv")
    with pytest.raises(AnalysisError, match="two or more conditions"):
        identification.correct_model(data[data["condition"] == "none"])
    with pytest.raises(AnalysisError, match="two or more participants"):
        identification.correct_model(data[data["participant"] == "P01"])
    with pytest.raises(AnalysisError, match="needs more participants than parameters"):
        identification.correct_model(data[data["participant"].isin(["P01", "P02", "P03"])])
    with pytest.raises(AnalysisError, match="must be 0/1"):
        identification.correct_model(data.assign(correct=data["correct"] * 2))
    with pytest.raises(AnalysisError, match="missing column"):
        identification.correct_model(data, covariates=("n_blink",))
    one_sided = data.assign(correct=data["correct"].where(data["condition"] != "composite", 1))
    with pytest.raises(AnalysisError, match=r"composite \(all right\) is the same"):
        identification.correct_model(one_sided)
    # a covariate that only marks the condition is dropped and named, not fitted
    marked = data.assign(n_blink=(data["condition"] == "composite").astype(int) * 3)
    got = identification.correct_model(marked, covariates=("n_gesture", "n_blink"))
    assert "n_blink" not in set(got["term"]) and "n_blink fixed by condition" in got["note"][0]


def test_stats_psychometric_contract_per_trial_and_per_level_agree():
    counts = pd.read_csv(REF / "psychometric_2afc.csv")
    per_level = counts.assign(correct=counts["k"] / counts["n"])[["level", "correct", "n"]]
    rows = [
        {"level": r.level, "correct": int(i < r.k)}
        for r in counts.itertuples()
        for i in range(int(r.n))
    ]
    a = stats.psychometric(pd.DataFrame(rows), level="level", correct="correct", n_boot=20)
    b = stats.psychometric(per_level, level="level", correct="correct", n_boot=20)
    assert list(a.columns[:8]) == [  # DESIGN.md's contract, then the fuller fit
        "subject",
        "n",
        "midpoint",
        "slope",
        "lapse",
        "deviance",
        "midpoint_ci_low",
        "midpoint_ci_high",
    ]
    assert list(a.columns) == list(stats.PSYCHOMETRIC_COLUMNS)
    pd.testing.assert_frame_equal(a, b)
    assert a.loc[0, "midpoint_ci_low"] < a.loc[0, "midpoint"] < a.loc[0, "midpoint_ci_high"]



def test_level_counts_are_count_responses_without_its_checks():
    """The calibration's counting of simulated sessions gives count_responses' table - trials
    at a missing level or without an answer left out - and refuses nothing itself."""
    rng = np.random.default_rng(3)
    level = rng.choice([0.1, 0.2, 0.4, 0.8, np.nan], size=300)
    y = rng.integers(0, 2, size=300).astype(float)
    y[::17] = np.nan
    checked = psychometric.count_responses(pd.DataFrame({"level": level, "y": y}), x="level",
                                           y="y")  # fmt: skip
    quick = psychometric.level_counts(level=level, y=y)
    pd.testing.assert_frame_equal(quick, checked)
    assert list(quick["level"]) == [0.1, 0.2, 0.4, 0.8] and quick["n"].sum() < 300
    assert psychometric.level_counts(level=np.array([]), y=np.array([])).empty
    with pytest.raises(AnalysisError, match="0/1"):  # the checks stay with count_responses
        psychometric.count_responses(pd.DataFrame({"level": [1.0], "y": [2.0]}), y="y")

def test_psychometric_fits_each_subject_and_the_pool_with_one_call():
    rng = np.random.default_rng(11)
    levels = np.repeat([0.1, 0.2, 0.3, 0.4, 0.5], 40)
    frames = []
    for subject, mid in (("s1", 0.25), ("s2", 0.35)):
        p = psychometric.predict(levels, sigmoid="logistic", alpha=mid, beta=20.0, gamma=0.5,
                                 lapse=0.0)  # fmt: skip
        frames.append(pd.DataFrame({"who": subject, "x": levels, "ok": rng.random(200) < p}))
    data = pd.concat(frames).astype({"ok": int})
    fits = stats.psychometric(data, level="x", correct="ok", subject="who", pooled=True, n_boot=0)
    assert list(fits["subject"]) == ["s1", "s2", "pooled"]
    assert fits["midpoint"].iloc[0] < fits["midpoint"].iloc[2] < fits["midpoint"].iloc[1]
    one_level = data[data["x"] == 0.3]
    failed = stats.psychometric(one_level, level="x", correct="ok", n_boot=0).iloc[0]
    assert not failed["converged"] and "two or more levels" in failed["note"]


def test_graded_functions_take_subject_and_still_the_old_participant_name():
    data = pd.read_csv(REF / "graded.csv").rename(columns={"participant": "who"})
    new = graded.trend_contrast(data, subject="who")
    with pytest.warns(DeprecationWarning, match="use subject="):
        old = graded.trend_contrast(data, participant="who")
    pd.testing.assert_frame_equal(new, old)
    assert "f" in new.columns and "F" not in new.columns


def test_fit_recovers_known_observer_within_its_ci():
    rng = np.random.default_rng(3)
    levels = np.linspace(0.0, 1.0, 8)
    truth = {"alpha": 0.42, "beta": 9.0, "lapse": 0.03}
    n = np.full(len(levels), 80)
    p = psychometric.predict(levels, sigmoid="logistic", gamma=0.5, **truth)
    counts = pd.DataFrame({"level": levels, "n": n, "k": rng.binomial(n, p)})
    fit = psychometric.fit_psychometric(counts, gamma=0.5, n_boot=300, rng=rng)
    assert fit.midpoint_ci_low <= truth["alpha"] <= fit.midpoint_ci_high
    assert fit.beta_ci_low <= truth["beta"] <= fit.beta_ci_high
    assert fit.lapse_ci_low <= truth["lapse"] <= fit.lapse_ci_high


def test_fit_reports_perfect_separation_instead_of_a_zero_width_ci():
    # chance at the two low levels, ceiling from 1.0 on: the likelihood is flat for any
    # midpoint between 0.75 and 1.0 and grows without end with the slope
    counts = pd.DataFrame(
        {"level": [0.25, 0.5, 0.75, 1.0, 1.5], "n": [8] * 5, "k": [4, 4, 4, 8, 8]}
    )
    fit = psychometric.fit_psychometric(counts, gamma=0.5, n_boot=40, rng=np.random.default_rng(0))
    assert "perfect separation" in fit.note and "between levels 0.75 and 1" in fit.note
    assert 0.75 <= fit.midpoint <= 1.0
    assert np.isnan(fit.midpoint_ci_low) and np.isnan(fit.midpoint_ci_high)
    assert np.isnan(fit.beta_ci_low) and np.isnan(fit.beta_ci_high)
    assert "range searched" not in fit.note  # no CI, so no note on its limits


def test_fit_marks_ci_limits_censored_by_the_search_range():
    # a shallow, noisy observer: many bootstrap refits put the midpoint far below the levels
    counts = pd.DataFrame({"level": [0.25, 0.5, 0.75, 1.0], "n": [10] * 4, "k": [7, 6, 8, 9]})
    fit = psychometric.fit_psychometric(counts, gamma=0.5, n_boot=200, rng=np.random.default_rng(1))
    assert fit.midpoint_ci_low == -np.inf
    assert "lower limit lies below the range searched (-1.25)" in fit.note
    assert np.isfinite(fit.midpoint)
    # a well-measured observer has finite limits and no note
    levels = np.linspace(0.0, 1.0, 6)
    p = psychometric.predict(levels, sigmoid="logistic", alpha=0.5, beta=12.0, gamma=0.5, lapse=0)
    good = pd.DataFrame({"level": levels, "n": 200, "k": np.round(200 * p).astype(int)})
    fit = psychometric.fit_psychometric(good, gamma=0.5, n_boot=100, rng=np.random.default_rng(2))
    assert np.isfinite([fit.midpoint_ci_low, fit.midpoint_ci_high]).all()
    assert fit.note == ""


def test_a_slope_the_levels_cannot_bound_has_an_open_interval_not_a_zero_width_one():
    """An observer right on nearly every trial at every level (its threshold below the grid):
    resampled slopes pile on the search bound, which gave intervals of zero width ([1818,
    1818]) at the bound; the interval's upper end is now open and named."""
    counts = pd.DataFrame({"level": [0.05, 0.1, 0.2, 0.3, 0.4, 0.6], "n": [25] * 6,
                           "k": [24, 25, 25, 25, 25, 25]})  # fmt: skip
    fit = psychometric.fit_psychometric(counts, gamma=0.5, n_boot=60, rng=np.random.default_rng(3))
    assert "perfect separation" not in fit.note
    assert "slope CI: its upper limit lies above the range searched" in fit.note
    assert fit.beta_ci_high == np.inf and fit.beta_ci_low < fit.beta_ci_high


def test_psychometric_refuses_bad_input():
    from facelab.errors import AnalysisError

    one_level = pd.DataFrame({"level": [0.3], "n": [10], "k": [7]})
    with pytest.raises(AnalysisError, match="two or more levels"):
        psychometric.fit_psychometric(one_level, gamma=0.5)
    with pytest.raises(AnalysisError, match="Weibull"):
        psychometric.fit_psychometric(
            pd.DataFrame({"level": [-1.0, 1.0], "n": [5, 5], "k": [3, 4]}),
            gamma=0.5,
            sigmoid="weibull",
        )


# --------------------------------------------------------------------------- protocol & design


def _protocol(tmp_path: Path, name: str, edit=lambda s: s):
    text = edit(protocol_path(name).read_text(encoding="utf-8"))
    path = tmp_path / f"{name}.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("name", "old", "new", "message"),
    [
        ("gain_2afc", "task: stronger", "task: weaker", "unknown task 'weaker'"),
        ("gain_2afc", "standard: g100", "standard: g999", "unknown condition 'g999'"),
        (
            "gain_2afc",
            "level: 0.1}",
            "}",
            "needs a 'level' on every condition of the block; missing on g110",
        ),
        (
            "gain_staircase",
            "    staircase: {rule: up_down, start: g160",
            "    staircase: {rule: up_down, start: g100",
            "start 'g100' is not among the block's conditions",
        ),
        ("gain_staircase", "    correct: comparison", "    correct: none", "adapts on correct"),
        (
            "gain_2afc",
            "    gap_s: 0.5",
            "    layout: side_by_side\n    gap_s: 0.5",
            "gap_s is the blank between sequential clips",
        ),
        ("gain_2afc", "    gap_s: 0.5", "    layout: beside", "'sequential' or 'side_by_side'"),
        (
            "method_identify",
            "emphasized: vowel_emphasized}",
            "emphasized: surprise}",
            "unknown label 'surprise'",
        ),
    ],
)
def test_protocol_checks_of_tasks_and_designs(tmp_path, name, old, new, message):
    path = _protocol(tmp_path, name, lambda s: s.replace(old, new, 1))
    with pytest.raises(ProtocolError, match=message):
        load_protocol(path)


def test_choice_design_counterbalances_the_comparison_position():
    protocol = load_protocol(protocol_path("gain_2afc"))
    frame = trials_frame(build_trials(protocol, participant="P03"))
    assert list(frame.columns[-2:]) == ["standard", "position"]
    assert (frame["standard"] == "g100").all() and "g100" not in set(frame["condition"])
    per_condition = frame.groupby("condition")["position"].value_counts().unstack()
    assert (per_condition[1] == per_condition[2]).all()  # 10 showings each: 5 first, 5 second
    # and the order differs between participants
    other = trials_frame(build_trials(protocol, participant="P04"))
    assert list(other["condition"]) != list(frame["condition"])


def test_staircase_design_leaves_the_level_to_run_time():
    protocol = load_protocol(protocol_path("gain_staircase"))
    trials = build_trials(protocol, participant="P01")
    assert len(trials) == 50 and {t.condition for t in trials} == {PENDING}
    assert Counter(t.position for t in trials) == {1: 25, 2: 25}


def test_vas_protocols_keep_their_design_columns():
    frame = trials_frame(build_trials(load_protocol(protocol_path("kato2021")), participant="P01"))
    assert list(frame.columns) == [
        "trial_index",
        "block",
        "set_index",
        "stimulus_set",
        "stimulus",
        "condition",
        "repetition",
    ]


# --------------------------------------------------------------------------- timeline & staircase


def test_choice_screen_scores_the_interval_that_held_the_comparison():
    protocol = load_protocol(protocol_path("gain_2afc"))
    trial = next(t for t in build_trials(protocol, participant="P01") if t.position == 2)
    clip1, clip2, choice = trial_screens(protocol, trial)
    assert clip1.clip[2] == "g100" and clip2.clip[2] == trial.condition  # comparison second
    assert (clip1.interval, clip2.interval) == (1, 2) and clip2.gap_s == 0.5
    ctx = SessionContext(
        study="gain2afc", participant="P01", session=1, simulated=True, protocol_sha256="x"
    )
    (row,) = choice.rows([ChoiceAnswer(2, 0.8, "t")], context=ctx, playback=None)
    assert (row["response"], row["correct"], row["position"]) == (trial.condition, 1, 2)
    assert row["comparison"] == "g100" and row["level"] == protocol.condition(trial.condition).level
    (row,) = choice.rows([ChoiceAnswer(1, 0.8, "t")], context=ctx, playback=None)
    assert (row["response"], row["correct"]) == ("g100", 0)
    assert isinstance(choice, ChoiceScreen)


def test_up_down_rule_and_its_convergence_point():
    s = UpDownStaircase(grid=("a", "b", "c", "d"), levels=(4, 3, 2, 1), start=0)
    moves = [(s.update(c), s.condition)[1] for c in (True, True, True, True, False, True, True)]
    assert moves == ["a", "b", "b", "c", "b", "b", "c"]
    assert s.reversals == [2, 3]  # harder -> easier at level 2, easier -> harder at level 3
    assert convergence_probability(up=1, down=2) == pytest.approx(0.7071, abs=1e-4)
    assert convergence_probability(up=1, down=3) == pytest.approx(0.7937, abs=1e-4)


def test_resumed_staircase_continues_the_same_staircase(tmp_path):
    path = protocol_path("gain_staircase")
    protocol = load_protocol(path)
    (paths,) = simulate_study(
        protocol, protocol_path=path, results=tmp_path, participants=1, seed=9
    )
    rows = load_results(tmp_path, study=protocol.study.id).sort_values("trial_index")
    records = rows.to_dict("records")
    trials = build_trials(protocol, participant="P01")
    for cut in (1, 7, 23, 49):
        resumed = Staircases(protocol, logged=records[:cut], record=None)
        assert resumed.resolve(trials[cut]) == records[cut]["condition"]
    # the step file agrees with the replay, and a log from another staircase is refused
    steps = [json.loads(x) for x in paths.staircase.read_text().splitlines()]
    assert [s["condition"] for s in steps] == [r["condition"] for r in records]
    Staircases(protocol, logged=records, record=paths.staircase)
    tampered = [dict(r) for r in records[:5]]
    tampered[3]["condition"] = "g105"
    with pytest.raises(SessionError, match="does not belong to this staircase"):
        Staircases(protocol, logged=tampered)
    start = new_staircase(protocol, "main")
    assert start.condition == "g160" and start.grid[0] == "g160"  # easiest (highest) first


def test_timeline_has_one_response_screen_per_task_trial():
    protocol = load_protocol(protocol_path("method_identify"))
    trials = build_trials(protocol, participant="P01")
    screens = compile_timeline(protocol, trials, participant="P01", session=1)
    keys = [k for s in screens for k in s.response_keys()]
    assert len(keys) == len(trials) == len(set(keys))


# --------------------------------------------------------------------------- end to end


def test_simulated_observers_are_recovered(tmp_path):
    rng = np.random.default_rng(4)
    for name in ("gain_2afc", "method_identify"):
        path = protocol_path(name)
        protocol = load_protocol(path)
        simulate_study(
            protocol, protocol_path=path, results=tmp_path / name, participants=10, seed=2
        )
        data = load_results(tmp_path / name, study=protocol.study.id)
        res = analyze_tasks(data, protocol, rng=rng, n_boot=200)
        if name == "gain_2afc":
            fits = res.tables["psychometric_fits"]
            pooled = fits[fits["participant"] == "pooled"].iloc[0]
            truth = protocol.simulation.observer
            assert pooled["midpoint_ci_low"] <= truth.midpoint <= pooled["midpoint_ci_high"]
            assert pooled["slope_ci_low"] <= truth.slope <= pooled["slope_ci_high"]
        else:
            summary = res.tables["identification_summary"]
            pooled = summary[summary["participant"] == "pooled"].iloc[0]
            confusion = protocol.simulation.identifier.confusion
            expected = np.mean([confusion[lb][lb] for lb in confusion])  # balanced design
            se = np.sqrt(expected * (1 - expected) / pooled["n"])
            assert abs(pooled["accuracy"] - expected) < 3 * se


def test_per_participant_intervals_are_calibrated_on_the_design(tmp_path):
    """With a design sampler (as `facelab analyze` passes), each participant's intervals end
    at the drops found by simulating the staircase at the pooled estimate - named in the
    note - and the pooled row is the same as without it (its bootstrap draws untouched)."""
    from facelab.experiment.simulate import design_sampler

    path = protocol_path("gain_staircase")
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path, participants=4, seed=5)
    data = load_results(tmp_path, study=protocol.study.id)
    plain = analyze_tasks(data, protocol, rng=np.random.default_rng(1), n_boot=20)
    cal = analyze_tasks(data, protocol, rng=np.random.default_rng(1), n_boot=20,
                        sampler=design_sampler(protocol))  # fmt: skip
    a = plain.tables["psychometric_fits"].set_index("participant")
    b = cal.tables["psychometric_fits"].set_index("participant")
    pd.testing.assert_series_equal(a.loc["pooled"], b.loc["pooled"])
    people = [p for p in a.index if p != "pooled"]
    assert len(people) == 4
    for p in people:
        assert "calibrated on the design" in b.loc[p, "note"]
        assert "calibrated" not in a.loc[p, "note"]
        assert b.loc[p, "midpoint"] == a.loc[p, "midpoint"]  # the same mode
        assert b.loc[p, "midpoint_ci_low"] <= b.loc[p, "midpoint"] <= b.loc[p, "midpoint_ci_high"]
    assert any(b.loc[p, "slope_ci_low"] != a.loc[p, "slope_ci_low"] for p in people)


def test_a_session_stopped_early_says_so_beside_its_calibrated_intervals(tmp_path):
    """P02 stopped after 20 of the staircase's 50 trials: its note says that it has 20 of
    the design's 50 trials and that the intervals were calibrated on complete sessions; the
    others' notes do not; everyone's intervals end at the same drops (one calibration)."""
    from facelab.analysis.tasks import calibrate_design, choice_outcome
    from facelab.experiment.simulate import design_sampler

    path = protocol_path("gain_staircase")
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path, participants=4, seed=5)
    data = load_results(tmp_path, study=protocol.study.id)
    task = protocol.tasks[0]
    mine = (data["participant"] == "P02") & (data["item"] == task.id)
    stopped = data.drop(index=data[mine].sort_values("trial_index").index[20:])
    res = analyze_tasks(stopped, protocol, rng=np.random.default_rng(1), n_boot=20,
                        sampler=design_sampler(protocol))  # fmt: skip
    fits = res.tables["psychometric_fits"].set_index("participant")
    assert fits.loc["P02", "n"] == 20
    assert "20 of the design's 50 trials (calibrated on complete" in fits.loc["P02", "note"]
    for p in ("P01", "P03", "P04"):
        assert "of the design's" not in fits.loc[p, "note"]
        assert fits.loc[p, "note"] == fits.loc["P01", "note"]
    assert fits.loc["P02", "note"].startswith(fits.loc["P01", "note"])

    rows = stopped[stopped["item"] == task.id]
    y, gamma = choice_outcome(rows, task)
    cal = calibrate_design(rows.assign(y=y.to_numpy()), task, gamma=gamma,
                           sampler=design_sampler(protocol), rng=np.random.default_rng(2),
                           n=40)  # fmt: skip
    assert cal is not None and cal.full_trials == 50 and len(cal.samples) == 40


def test_identification_is_compared_between_conditions(tmp_path):
    """Emotions portrayed under two behaviour conditions (seed 003): simulated identifiers
    name the emotion more often under composite behaviour; the analysis finds it."""
    path = protocol_path("hattori_behaviour")
    protocol = load_protocol(path)
    truth = protocol.simulation.identifier.condition_accuracy
    simulate_study(protocol, protocol_path=path, results=tmp_path, participants=30, seed=8)
    data = load_results(tmp_path, study=protocol.study.id)
    res = analyze_tasks(data, protocol, rng=np.random.default_rng(1), n_boot=20)
    by = res.tables["identification_by_condition"].set_index("condition")
    assert list(by.index) == ["gestures_only", "composite"]  # the protocol's order
    for cond, p in truth.items():
        se = np.sqrt(p * (1 - p) / by.loc[cond, "n"])
        assert abs(by.loc[cond, "accuracy"] - p) < 3 * se
    model = res.tables["identification_condition_model"].set_index("term")
    effect = model.loc["C(condition)[T.composite]"]
    log_or = np.log(truth["composite"] / (1 - truth["composite"])) - np.log(
        truth["gestures_only"] / (1 - truth["gestures_only"])
    )
    assert effect["p"] < 0.001
    assert effect["estimate"] - 3 * effect["se"] < log_or < effect["estimate"] + 3 * effect["se"]
    ((task, matrices),) = res.confusion_by_condition
    assert task.id == "which_emotion" and list(matrices) == ["gestures_only", "composite"]
    for cond, m in matrices.items():
        assert int(np.trace(m.to_numpy())) == round(by.loc[cond, "accuracy"] * by.loc[cond, "n"])
    # method_identify's answer is the condition itself: nothing to compare between conditions
    other = protocol_path("method_identify")
    simulate_study(
        load_protocol(other), protocol_path=other, results=tmp_path / "m", participants=3, seed=1
    )
    res = analyze_tasks(
        load_results(tmp_path / "m", study=load_protocol(other).study.id),
        load_protocol(other),
        rng=np.random.default_rng(1),
        n_boot=20,
    )
    assert "identification_by_condition" not in res.tables and not res.confusion_by_condition


@pytest.mark.parametrize("name", EXAMPLES)
def test_example_protocol_simulates_and_analyses(tmp_path, name, capsys):
    path = protocol_path(name)
    assert main(["validate", str(path)]) == 0
    results = tmp_path / "results"
    assert (
        main(
            ["simulate", str(path), "--participants", "6", "--sim-seed", "1",
             "--results", str(results)]
        )
        == 0
    )
    out = tmp_path / "analysis"
    assert (
        main(
            [
                "analyze",
                str(path),
                str(results),
                "--force",
                "--out",
                str(out),
                "--bootstrap",
                "50",
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    expected = {
        "gain_2afc": ["psychometric_fits.csv", "fig_psychometric_stronger.png"],
        "gain_staircase": [
            "staircase_thresholds.csv",
            "staircase_tracks.csv",
            "fig_staircase_main.png",
        ],
        "gain_questplus": [
            "staircase_thresholds.csv",
            "staircase_tracks.csv",
            "fig_staircase_main.png",
        ],
        "horii_impression_side": ["psychometric_fits.csv", "fig_psychometric_friendlier.png"],
        "method_identify": ["identification_summary.csv", "fig_confusion_which_method.png"],
        "gain_vas": ["trend_contrast.csv", "graded_lmm.csv", "rm_anova.csv"],
    }[name]
    for file in expected:
        assert (out / file).exists(), file
    if (out / "staircase_tracks.csv").exists():  # every step of every participant, once
        track = pd.read_csv(out / "staircase_tracks.csv")
        thresholds = pd.read_csv(out / "staircase_thresholds.csv")
        per = track.groupby("participant").agg(
            trials=("step", "size"), reversals=("reversal", "sum")
        )
        merged = thresholds.set_index("participant")[["trials", "reversals"]]
        pd.testing.assert_frame_equal(per.sort_index(), merged.sort_index(), check_dtype=False)
        last = track.sort_values("step").groupby("participant")["threshold"].last()
        np.testing.assert_allclose(
            last.sort_index(), thresholds.set_index("participant")["threshold"].sort_index()
        )
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "SIMULATED" in report
    assert "note: no responses for condition" not in printed


def test_an_identification_staircase_is_analysed(tmp_path):
    """A staircase may adapt on identification answers (guess rate 1/k): its thresholds and
    tracks are tabled like a forced choice's."""

    def to_identify(text: str) -> str:
        start, end = text.index("tasks:\n"), text.index("blocks:\n")
        task = (
            "tasks:\n  - id: stronger\n    type: identify\n    question: {ja: どちら, en: Which?}\n"
            "    labels: [{id: weak, text: {ja: 弱, en: weak}},"
            " {id: strong, text: {ja: 強, en: strong}}]\n"
            "    answers: {g105: weak, g110: weak, g120: weak, g130: strong, g140: strong,"
            " g160: strong}\n\n"
        )
        text = text[:start] + task + text[end:]
        return text.replace("trials: 50, easier: higher}", "trials: 12, easier: higher}\n"
                            "    conditions: [g105, g110, g120, g130, g140, g160]")  # fmt: skip

    path = _protocol(tmp_path, "gain_staircase", to_identify)
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path / "r", participants=3, seed=2)
    data = load_results(tmp_path / "r", study=protocol.study.id)
    res = analyze_tasks(data, protocol, rng=np.random.default_rng(0), n_boot=0)
    thresholds = res.tables["staircase_thresholds"]
    assert list(thresholds["trials"]) == [12, 12, 12]
    assert len(res.tables["staircase_tracks"]) == 36 and len(res.staircases) == 1
    assert "identification_summary" in res.tables


def test_condition_model_with_identical_answers_in_both_conditions_tests_as_no_difference():
    # every participant answered alike in both conditions: estimate 0 and SE 0, so t is 0/0;
    # it is reported as t = 0, p = 1 (not a random p from rounding noise)
    rows = []
    for k, right in enumerate([3, 5, 6, 8]):
        for cond in ("a", "b"):
            rows += [
                {"participant": f"P{k}", "condition": cond, "correct": int(i < right)}
                for i in range(12)
            ]
    got = identification.correct_model(pd.DataFrame(rows), conditions=["a", "b"])
    term = got.set_index("term").loc["C(condition)[T.b]"]
    assert abs(term["estimate"]) < 1e-8 and term["se"] < 1e-8
    assert term["t"] == 0.0 and term["p"] == 1.0


@pytest.mark.parametrize(
    ("name", "observer", "where", "share"),
    [
        ("gain_staircase", "{midpoint: -0.5, slope: 40, lapse: 0.0, midpoint_sd: 0.0}",
         r"(the track kept to|at) the grid's hardest level \(0.05\)", 0.9),
        ("gain_staircase", "{midpoint: 3.0, slope: 18, lapse: 0.03, midpoint_sd: 0.0}",
         r"((the track kept to|at) the grid's easiest level \(0.6\)|\d+ of \d+ right over "
         r"the whole track, fewer than the rule converges on)", 0.6),
        ("gain_questplus", "{midpoint: 3.0, slope: 18, lapse: 0.03, midpoint_sd: 0.0}",
         r"(the posterior's most likely threshold is the end of its grid \(0.6,|at the grid's "
         r"easiest level \(0.6\))", 0.4),
        ("gain_questplus", "{midpoint: -0.5, slope: 40, lapse: 0.0, midpoint_sd: 0.0}",
         r"(the posterior's most likely threshold is the end of its grid \(0.05,|at the "
         r"grid's hardest level \(0.05\))", 0.8),
    ],
)  # fmt: skip
def test_a_threshold_beyond_the_levels_rendered_is_named_a_bound(
    tmp_path, name, observer, where, share
):
    """Observers whose threshold lies beyond the grid (far better or far worse than its
    ends): each staircase row's note says the threshold is a bound, not an estimate - the
    rule's own number (a mean of reversals at the grid's end, a QUEST+ posterior mean with a
    small SD) would otherwise read as a precise threshold. Observers inside stay un-noted.
    Over 150 simulated observers (stop 82): up-down 144 / 150 of 150 named beyond the easy /
    hard end, QUEST+ 88 / 141 (its 30 trials often leave a chance observer's posterior
    spread; facelab's simulated participants here: 9 of 12 up-down beyond the easy end);
    inside the grid 2 / 0 of 150 at the shipped truth."""
    shipped = "{midpoint: 0.18, slope: 18, lapse: 0.03, midpoint_sd: 0.0}"
    path = _protocol(tmp_path, name, lambda s: s.replace(shipped, observer))
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path / "r", participants=12,
                   seed=2)  # fmt: skip
    data = load_results(tmp_path / "r", study=protocol.study.id)
    res = analyze_tasks(data, protocol, rng=np.random.default_rng(0), n_boot=0)
    notes = res.tables["staircase_thresholds"]["note"]
    # an observer at chance can, by luck, answer like one whose threshold is inside the grid
    named = notes.str.match(where)
    assert named.mean() >= share and (named | notes.eq("")).all(), notes.tolist()
    (tmp_path / "in").mkdir()  # the shipped observer, inside the grid: false alarms are rare
    inside = _protocol(tmp_path / "in", name)
    protocol = load_protocol(inside)
    simulate_study(protocol, protocol_path=inside, results=tmp_path / "r2", participants=20,
                   seed=2)  # fmt: skip
    data = load_results(tmp_path / "r2", study=protocol.study.id)
    res = analyze_tasks(data, protocol, rng=np.random.default_rng(0), n_boot=0)
    assert res.tables["staircase_thresholds"]["note"].ne("").sum() <= 1  # 2/150 and 0/150


def test_a_participants_second_staircase_session_is_its_own_staircase(tmp_path, capsys):
    """A participant who ran the staircase twice (a retest): each session is replayed as the
    staircase it ran - the two were read as one track and refused as a log 'not belonging
    to this staircase' - and both thresholds are tabled, by session."""
    from tests.session_edits import rewrite_rows

    path = _protocol(tmp_path, "gain_staircase")
    protocol = load_protocol(path)
    simulate_study(protocol, protocol_path=path, results=tmp_path / "r", participants=2, seed=2)
    first = next((tmp_path / "r").rglob("sub-P01/ses-1"))
    second = first.with_name("ses-2")
    second.mkdir()
    for f in first.iterdir():
        (second / f.name.replace("ses-1", "ses-2")).write_bytes(f.read_bytes())
    rewrite_rows(second, lambda row: row.update(session="2") is None)
    (session,) = second.glob("*_session.json")
    session.write_text(session.read_text(encoding="utf-8").replace('"session": 1',
                                                                   '"session": 2'))  # fmt: skip
    out = tmp_path / "a"
    assert main(["analyze", str(path), str(tmp_path / "r"), "--out", str(out), "--bootstrap",
                 "0"]) == 0  # fmt: skip
    assert "P01: sessions 1, 2" in capsys.readouterr().out
    thresholds = pd.read_csv(out / "staircase_thresholds.csv")
    assert list(zip(thresholds["participant"], thresholds["session"], strict=True)) == [
        ("P01", 1), ("P01", 2), ("P02", 1)]  # fmt: skip
    one = thresholds[thresholds["participant"] == "P01"]
    assert one["threshold"].nunique() == 1  # the same answers, the same staircase
