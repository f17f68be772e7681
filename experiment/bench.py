"""``facelab bench analyze``: the analysis at the scale of online studies.

Simulates N participants of a protocol once (not timed), then times ``facelab analyze`` on
them as a user runs it (a new process, imports included), ``runs`` times; prints the median
and every run. It also checks that the fast path gives the same numbers: the mixed-model F
by the closed form against a statsmodels MixedLM fit on the first 50 participants (where the
protocol has rating items; for a choice-only protocol those fields are null).
"""

from __future__ import annotations

import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from facelab.errors import StageError

__all__ = ["bench_analyze"]


def bench_analyze(*, protocol: Path, participants: int = 1000, runs: int = 3) -> dict[str, Any]:
    from facelab.analysis import stats
    from facelab.analysis.load import load_results
    from facelab.experiment.simulate import simulate_study
    from facelab.protocol import load_protocol

    proto = load_protocol(protocol)
    exe = str(Path(sys.executable).with_name("facelab"))
    with tempfile.TemporaryDirectory(prefix="facelab-bench-") as tmp:
        results = Path(tmp) / "results"
        t0 = time.perf_counter()
        simulate_study(
            proto, protocol_path=protocol, results=results, participants=participants, seed=1
        )
        simulate_s = time.perf_counter() - t0
        times = []
        for i in range(runs):
            t0 = time.perf_counter()
            done = subprocess.run(
                [
                    exe,
                    "analyze",
                    str(protocol),
                    str(results),
                    "--out",
                    str(Path(tmp) / f"analysis{i}"),
                ],
                capture_output=True,
                text=True,
                check=False,
            )
            times.append(time.perf_counter() - t0)
            if done.returncode != 0:
                raise StageError(f"facelab analyze failed: {done.stderr[-800:]}")
        forced_choice = _forced_choice_analysis(Path(tmp), exe)
        data = load_results(results, study=proto.study.id)
        closed = fitted = difference = None
        if proto.items:  # the mixed-model check needs ratings (a choice-only protocol has none)
            first = sorted(data["participant"].unique())[:50]
            sub = data[
                data["participant"].isin(first)
                & (data["item"] == proto.items[0].id)
                & (data["stimulus_set"] == proto.stimulus_sets[0].id)
            ]
            kw = {"dv": "rating", "within": "condition", "subject": "participant"}
            closed = float(stats.lmm_anova(sub, **kw)["f"].iloc[0])
            fitted = float(stats.lmm_anova(sub, closed_form=False, **kw)["f"].iloc[0])
            difference = abs(closed - fitted) / fitted
    return {
        "benchmark": "analyze",
        "protocol": str(protocol),
        "participants": participants,
        "responses": len(data),
        "simulate_s": round(simulate_s, 2),
        "analyze_s_median": round(statistics.median(times), 2),
        "analyze_s_runs": [round(t, 2) for t in times],
        "target_s": 5.0,
        "lmm_f_closed_form_50": closed,
        "lmm_f_mixedlm_fit_50": fitted,
        "lmm_f_relative_difference": difference,
        "forced_choice": forced_choice,
    }


def _forced_choice_analysis(tmp: Path, exe: str) -> dict[str, Any]:
    """``facelab analyze`` of the shipped 2AFC protocol (8 simulated participants x 60
    trials) with its default intervals (parametric bootstrap, 200 resamples per fit)."""
    from facelab.experiment.simulate import simulate_study
    from facelab.protocol import load_protocol
    from facelab.resources import protocol_path

    path = protocol_path("gain_2afc")
    results = tmp / "fc"
    simulate_study(load_protocol(path), protocol_path=path, results=results, participants=8,
                   seed=1)  # fmt: skip
    t0 = time.perf_counter()
    done = subprocess.run(
        [exe, "analyze", str(path), str(results), "--out", str(tmp / "fc-analysis")],
        capture_output=True,
        text=True,
        check=False,
    )
    seconds = time.perf_counter() - t0
    if done.returncode != 0:
        raise StageError(f"facelab analyze failed: {done.stderr[-800:]}")
    return {"protocol": "gain_2afc", "participants": 8, "trials_each": 60,
            "bootstrap": 200, "analyze_s": round(seconds, 2), "target_s": 10.0}  # fmt: skip
