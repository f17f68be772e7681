"""Power: the non-central F formula against simulation, and the CLI in both modes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from scipy import stats as sps

from facelab.analysis import power
from facelab.errors import AnalysisError
from facelab.experiment.cli import main


def test_implied_effect_inverts_the_f_test() -> None:
    est = power.implied_effect(p=0.0159099583256229, df1=2, df2=27)  # PlantGrowth (R)
    assert est["f"] == pytest.approx(4.84608786238014, rel=1e-9)
    assert est["eta_p_sq"] == pytest.approx(0.26414829683212, rel=1e-9)


@pytest.mark.parametrize(("n", "k", "f2"), [(8, 3, 0.3), (12, 3, 0.15), (10, 4, 0.2)])
def test_formula_agrees_with_simulation(n: int, k: int, f2: float) -> None:
    rng = np.random.default_rng(n * 100 + k)
    sims = 6000
    formula = power.rm_power(n=n, k=k, f2=f2)
    simulated = power.simulate_power(n=n, k=k, f2=f2, sims=sims, rng=rng)
    se = np.sqrt(formula * (1 - formula) / sims)
    assert abs(simulated - formula) < 4 * se


def test_null_effect_has_alpha_power_and_needed_n_is_minimal() -> None:
    assert power.simulate_power(
        n=8, k=3, f2=0.0, sims=8000, rng=np.random.default_rng(1)
    ) == pytest.approx(0.05, abs=0.01)
    n = power.participants_needed(k=3, f2=0.25, power=0.8)
    assert n is not None
    assert power.rm_power(n=n, k=3, f2=0.25) >= 0.8 > power.rm_power(n=n - 1, k=3, f2=0.25)
    assert power.participants_needed(k=3, f2=0.0) is None


def test_reported_p_conversion_states_its_assumptions(capsys: pytest.CaptureFixture[str]) -> None:
    assert (
        main(
            [
                "power",
                "--reported-p",
                "0.0053",
                "--reported-n",
                "8",
                "--reps",
                "2",
                "--json",
                "--sims",
                "500",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    row = out["rows"][0]
    assert row["f"] == pytest.approx(sps.f.isf(0.0053, 2, 45))
    assert "assumed variance split" in out["assumptions"]
    assert row["n_needed"] >= 2 and 0.7 < row["simulated_power_at_needed"] < 0.95
    assert main(["power"]) == 2
    assert main(["power", "--reported-p", "1.5"]) == 2


def test_power_from_pilot_logs(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(
            [
                "simulate",
                str(kato_path),
                "--participants",
                "8",
                "--sim-seed",
                "5",
                "--results",
                str(tmp_path),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(["power", str(kato_path), "--pilot", str(tmp_path), "--sims", "500"])
        == 0
    )
    out = capsys.readouterr().out
    assert out.count("pilot F") == 4 and "mouth_shape/sentences" in out


def test_pilot_power_points_forced_choice_studies_to_simulation(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from facelab.resources import protocol_path

    proto = str(protocol_path("gain_2afc"))
    argv = ["simulate", proto, "--participants", "3", "--sim-seed", "1", "--results", str(tmp_path)]
    assert main(argv) == 0
    capsys.readouterr()
    assert main(["power", proto, "--pilot", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "no VAS ratings" in err and "--simulate" in err and "facelab power " in err


@pytest.mark.parametrize("p", [0.0, 1.0, 1.5, -0.1])
def test_reported_p_outside_0_1_is_refused(p: float, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["power", "--reported-p", str(p)]) == 2
    assert "strictly between 0 and 1" in capsys.readouterr().err


def test_large_p_implies_no_effect_and_power_is_alpha(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["power", "--reported-p", "0.7", "--sims", "100"]) == 0
    out = capsys.readouterr().out
    assert "power with n=8: 0.050" in out and "cannot be computed" in out
    assert power.rm_power(n=8, k=3, f2=0.0) == pytest.approx(0.05)


def test_tiny_p_stays_finite_and_exact() -> None:
    from scipy import stats as sps

    for p in (1e-17, 1e-40, 1e-120):
        est = power.implied_effect(p=p, df1=2, df2=45)
        assert np.isfinite(est["f"]) and 0 < est["eta_p_sq"] < 1
        assert sps.f.logsf(est["f"], 2, 45) == pytest.approx(np.log(p), rel=1e-9)


# ------------------------------------------------------------- power of a protocol, simulated

_TWO_CONDITIONS = """
schema_version: 1
study: {id: pow, title: power test, participants_planned: 20}
seed: 4
conditions:
  - {id: a, label: {en: a}, method: vowel_blend, params: {z: standard}}
  - {id: b, label: {en: b}, method: vowel_blend, params: {z: emphasized}}
stimulus_sets:
  - id: s
    stimuli:
      - {id: s1, text: あ。}
      - {id: s2, text: い。}
      - {id: s3, text: う。}
      - {id: s4, text: え。}
blocks:
  - {id: main, stimulus_set: s, sets: 1, presentations_per_condition: 1}
items:
  - {id: natural, question: {en: natural?}, left_anchor: {en: not}, right_anchor: {en: very}}
presentation: {language: en}
simulation:
  model: {mean: 50, participant_sd: 8, interaction_sd: 3, noise_sd: 10}
  effects: {a: 0, b: 4}
"""


@pytest.mark.slow
def test_simulated_power_of_a_protocol_matches_the_formula(tmp_path: Path) -> None:
    """The whole pipeline (design, timeline, simulated answers, RM ANOVA) at n = 20 against
    the non-central F formula with f2 from the simulation model: 4 ratings per cell, so
    sigma_e^2 = 3^2 + 10^2 / 4 and f2 = 2^2 / sigma_e^2 (effects 0 and 4)."""
    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol

    path = tmp_path / "pow.yaml"
    path.write_text(_TWO_CONDITIONS, encoding="utf-8")
    protocol = load_protocol(path)
    sims = 400
    result = simulated_power(protocol, n_values=[20], sims=sims, rng=np.random.default_rng(7))
    assert result.precision.empty  # no forced-choice task
    (row,) = result.power.itertuples()
    assert (row.test, row.kind, row.n, row.failed) == ("natural/s", "rm_anova", 20, 0)
    formula = power.rm_power(n=20, k=2, f2=4.0 / (9.0 + 100.0 / 4))
    assert 0.3 < formula < 0.8  # a regime where the comparison can fail
    assert abs(row.power - formula) < 3 * np.sqrt(formula * (1 - formula) / sims)


@pytest.mark.slow
def test_simulated_identification_test_keeps_alpha_with_few_participants() -> None:
    """No true difference between the behaviour conditions: the identification GEE's
    small-sample test rejects in at most alpha of simulated 8-participant studies (the plain
    sandwich z test rejected in about 10 %)."""
    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    protocol = load_protocol(protocol_path("hattori_behaviour"))
    sim = protocol.simulation.model_copy(
        update={
            "identifier": protocol.simulation.identifier.model_copy(
                update={"condition_accuracy": {"gestures_only": 0.45, "composite": 0.45}}
            )
        }
    )
    protocol = protocol.model_copy(update={"simulation": sim})
    sims = 200
    table = simulated_power(protocol, n_values=[8], sims=sims, rng=np.random.default_rng(2)).power
    ident = table[table["kind"] == "identification"].iloc[0]
    assert ident["power"] <= 0.05 + 2 * np.sqrt(0.05 * 0.95 / sims)


@pytest.mark.slow
def test_power_simulate_cli(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "pow.yaml"
    path.write_text(_TWO_CONDITIONS, encoding="utf-8")
    args = ["power", str(path), "--simulate", "--n", "6", "30", "--sims", "60"]
    assert main([*args, "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    rows = {r["n"]: r for r in out["rows"]}
    assert set(rows) == {6, 30} and rows[30]["power"] > rows[6]["power"]
    assert out["assumptions"]["effects"] == {"a": 0.0, "b": 4.0}
    assert main([*args, "--effect", "b=0", "--json"]) == 0  # no effect: power near alpha
    null = json.loads(capsys.readouterr().out)
    assert null["assumptions"]["effects"] == {"a": 0.0, "b": 0.0}
    assert {r["n"]: r["power"] for r in null["rows"]}[30] < rows[30]["power"]
    assert main([*args, "--effect", "c=3"]) == 2
    assert "no such condition" in capsys.readouterr().err
    assert main([*args, "--plot", str(tmp_path / "power.png")]) == 0
    assert (tmp_path / "power.png").stat().st_size > 10_000
    text = capsys.readouterr().out
    assert "natural/s" in text and "rm_anova" in text and "n for 0.8" in text
    assert main([*args, "--plot", str(tmp_path / "no" / "p.png")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["power", str(path), "--simulate", "--n", "1"]) == 2
    assert "2 or more" in capsys.readouterr().err
    assert main(["power", str(path), "--simulate", "--reported-p", "0.01"]) == 2
    assert "leave out --pilot and --reported-p" in capsys.readouterr().err
    no_test = _TWO_CONDITIONS.replace("  - {id: b, label: {en: b}, method: vowel_blend, "
                                      "params: {z: emphasized}}\n", "")  # fmt: skip
    no_test = no_test.replace("effects: {a: 0, b: 4}", "effects: {a: 0}")
    path.write_text(no_test, encoding="utf-8")
    assert main(["power", str(path), "--simulate", "--sims", "5"]) == 2
    assert "nothing to simulate" in capsys.readouterr().err


@pytest.mark.slow
def test_simulated_threshold_precision_of_a_forced_choice_protocol(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """gain_2afc: the pooled midpoint of simulated studies centres on the observer's midpoint,
    and its SD across studies shrinks with more participants (about 1/sqrt(n))."""
    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    protocol = load_protocol(protocol_path("gain_2afc"))
    sims = 40
    result = simulated_power(protocol, n_values=[4, 16], sims=sims, rng=np.random.default_rng(3))
    assert result.power.empty
    prec = result.precision.set_index("n")
    truth = protocol.simulation.observer.midpoint
    for n in (4, 16):
        row = prec.loc[n]
        assert row["failed"] <= 2 and row["truth"] == truth
        assert abs(row["mean"] - truth) < 3 * row["sd"] / np.sqrt(sims - row["failed"])
        assert row["rmse"] == pytest.approx(np.hypot(row["sd"], row["mean"] - truth), rel=0.05)
    assert 1.3 < prec.loc[4, "sd"] / prec.loc[16, "sd"] < 3.2  # sqrt(16 / 4) = 2
    path = str(protocol_path("gain_2afc"))
    assert main(["power", path, "--simulate", "--n", "4", "--sims", "5"]) == 0
    out = capsys.readouterr().out
    assert "precision of the pooled psychometric midpoint" in out and "stronger midpoint" in out


def test_simulated_power_does_not_depend_on_the_number_of_processes(tmp_path: Path) -> None:
    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol

    path = tmp_path / "pow.yaml"
    path.write_text(_TWO_CONDITIONS, encoding="utf-8")
    protocol = load_protocol(path)
    one, two = (
        simulated_power(
            protocol, n_values=[6, 10], sims=24, rng=np.random.default_rng(5), jobs=jobs
        ).power
        for jobs in (1, 2)
    )
    assert one.equals(two) and one["power"].between(0, 1).all()


def test_one_participant_pilot_powers_with_its_own_repeats_and_says_so(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["simulate", str(kato_path), "--participants", "1", "--sim-seed", "1"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    capsys.readouterr()
    assert main(["power", str(kato_path), "--pilot", str(tmp_path), "--sims", "100"]) == 0
    out = capsys.readouterr().out
    assert "ONE participant" in out and "optimistic" in out and out.count("f2_rm") == 4


def test_one_participant_effect_size_is_the_spread_over_the_repeat_error() -> None:
    data = pd.DataFrame(
        {"condition": ["a", "a", "b", "b", "c", "c"], "rating": [10, 20, 40, 50, 70, 80]}
    )
    est = power.f2_from_one(data)
    # means 15, 45, 75: spread 600; within-condition variance 50, over 2 ratings: 25
    assert est["f2_raw"] == pytest.approx(600 / 25)
    assert est["f2_rm"] == pytest.approx(600 / 25 - 2 / 3)
    assert est["f_pilot"] == pytest.approx((2 * 1800 / 2) / 50)
    with pytest.raises(AnalysisError, match="2 or more ratings of every condition"):
        power.f2_from_one(data.iloc[1:])


def test_power_simulate_analyses_a_study_as_facelab_analyze_does(tmp_path: Path) -> None:
    """One analysis path: a simulated study in which one participant lacks a condition gets
    the same RM ANOVA p from power --simulate's tests as from facelab analyze's table (that
    participant left out by both), not a failed fit."""
    from facelab.analysis.load import frame_from_rows
    from facelab.analysis.study import analyze_study
    from facelab.experiment.simulate import simulated_rows
    from facelab.experiment.simulated_power import protocol_tests
    from facelab.protocol import load_protocol

    path = tmp_path / "pow.yaml"
    path.write_text(_TWO_CONDITIONS, encoding="utf-8")
    protocol = load_protocol(path)
    rng = np.random.default_rng(11)
    rows = [r for k, child in enumerate(rng.spawn(8))
            for r in simulated_rows(protocol, participant=f"P{k}", rng=child)]  # fmt: skip
    data = frame_from_rows(rows)
    data = data[~((data["participant"] == "P3") & (data["condition"] == "b"))]  # P3 lacks b
    tests = protocol_tests(data, protocol)
    study = analyze_study(data[data["screen"].fillna("vas") == "vas"], protocol)
    table = study.rm_anova.set_index(["item", "stimulus_set"])
    p_analyze = float(table.loc[("natural", "s"), "p_gg"])
    assert np.isfinite(tests[("natural/s", "rm_anova")])
    assert tests[("natural/s", "rm_anova")] == pytest.approx(p_analyze, rel=1e-12)
    assert any("P3" in n and "lack a condition" in n for n in study.notes)


def test_the_analysis_and_power_studies_hold_blas_to_one_thread(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """Their many small fits run with one BLAS thread (facelab.blas_threads: with OpenBLAS's
    spinning threads `facelab power --simulate` of kato2021_sync took 130 s, with one 11 s),
    whatever the caller allowed."""
    from threadpoolctl import threadpool_info, threadpool_limits

    from facelab.analysis import pipeline
    from facelab.experiment import simulated_power as power_module
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    class SeenError(Exception):
        pass

    seen: list[list[int]] = []

    def look(*args: object, **kwargs: object) -> None:
        seen.append([i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"])
        raise SeenError

    path = protocol_path("kato2021_sync")
    protocol = load_protocol(path)
    monkeypatch.setattr(pipeline, "load_results", look)
    monkeypatch.setattr(power_module, "frame_from_rows", look)
    with threadpool_limits(limits=2, user_api="blas"):
        allowed = [i["num_threads"] for i in threadpool_info() if i["user_api"] == "blas"]
        with pytest.raises(SeenError):
            pipeline.run(tmp_path, protocol, protocol_path=path, out=tmp_path / "out")
        with pytest.raises(SeenError):
            power_module._one_study((protocol, ["P1", "P2"], np.random.default_rng(1), None))
    assert allowed and max(allowed) == 2  # the test can fail: the caller allowed two
    assert seen == [[1] * len(allowed)] * 2


def test_a_pilot_without_participant_by_condition_error_is_named_not_infinite(
    tmp_path: Path, kato_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ratings whose condition means differ by the same amounts in every participant (made-up
    or test data) or that never differ give no effect size: that item is named not
    estimable, the others are powered, and nothing infinite or NaN (nor a numpy warning)
    reaches the terminal or the JSON."""
    import json
    import warnings

    from tests.session_edits import rewrite_ratings

    argv = ["simulate", str(kato_path), "--participants", "4", "--sim-seed", "5"]
    assert main([*argv, "--results", str(tmp_path)]) == 0
    rewrite_ratings(tmp_path, item="mouth_shape", stimulus_set="vowels",
                    rating=lambda row: {"baseline": 30, "standard": 50,
                                        "emphasized": 70}[row["condition"]])  # fmt: skip
    rewrite_ratings(tmp_path, item="naturalness", stimulus_set="vowels", rating=lambda row: 50)
    capsys.readouterr()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert main(["power", str(kato_path), "--pilot", str(tmp_path), "--sims", "200"]) == 0
    out = capsys.readouterr()
    assert "mouth_shape/vowels: not estimable - every participant's condition means differ " \
        "by exactly the same amounts" in out.out
    assert "naturalness/vowels: not estimable - every participant rated the conditions " \
        "alike" in out.out
    assert out.out.count("pilot F") == 2 and "inf" not in out.out and "nan" not in out.out
    assert main(["power", str(kato_path), "--pilot", str(tmp_path), "--sims", "200",
                 "--json"]) == 0  # fmt: skip
    rows = json.loads(capsys.readouterr().out, parse_constant=lambda c: pytest.fail(c))["rows"]
    assert sum("not_estimable" in r for r in rows) == 2


def test_a_test_no_simulated_study_could_run_is_shown_not_applicable(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Two participants cannot give the SRT comparison (it needs three): its power cell says
    n/a, not a power of 0.00, and the note says why."""
    path = Path(__file__).resolve().parents[1] / "protocols" / "kato2021_srt.yaml"
    assert main(["power", str(path), "--simulate", "--n", "2", "3", "--sims", "3",
                 "--sim-seed", "1"]) == 0  # fmt: skip
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if "srt_db between series" in line)
    assert row.split()[-4] == "n/a" and "n=2: 3 of 3 fits failed - n/a" in out
