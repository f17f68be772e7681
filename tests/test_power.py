"""Power: the non-central F formula against simulation, and the CLI in both modes."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats as sps

from facelab.analysis import power
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
                "--participants",
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
                "--seed",
                "5",
                "--results",
                str(tmp_path),
            ]
        )
        == 0
    )
    capsys.readouterr()
    assert (
        main(["power", "--pilot", str(tmp_path), "--protocol", str(kato_path), "--sims", "500"])
        == 0
    )
    out = capsys.readouterr().out
    assert out.count("pilot F") == 4 and "mouth_shape/sentences" in out


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
