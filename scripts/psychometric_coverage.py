"""Coverage of per-participant psychometric intervals on simulated observers (issue 34.2).

Simulates N observers of a shipped forced-choice protocol (its ``simulation.observer`` is the
truth) through the protocol's own design - staircase or constant stimuli - and fits each
participant three ways: maximum likelihood with parametric-bootstrap percentile intervals
(``ml_bootstrap``), and the grid posterior with psignifit's default priors
(:mod:`facelab.analysis.bayes_psychometric`) summarised by its mode and profile intervals
(``profile``), the same with the interval ends calibrated on the design
(``calibrated``, the per-participant default of ``facelab analyze``: the observers are taken
in studies of ``--group`` participants, each study's pooled estimate simulated through the
protocol's design 200 times; :func:`facelab.analysis.tasks.calibrate_design`), or by marginal
medians and credible intervals (``credible``). Prints JSON: for each estimator the share of
observers whose 95 % interval holds the true midpoint and slope, and the median estimate.

    python scripts/psychometric_coverage.py [PROTOCOL] [--observers 200] [--seed 7] [--boot 200]
        [--midpoint M] [--slope B] [--lapse L] [--group 8]
        [--estimators calibrated profile credible ml_bootstrap]
        [--stop-after K]

``--stop-after K`` cuts every session after K trials (sessions stopped early; ``calibrated``
still simulates complete sessions, as ``facelab analyze`` does). ``--midpoint/--slope/
--lapse`` replace the protocol's observer, to measure coverage at other truths:
per-participant coverage depends on the truth (a slope steeper than the levels' spacing can
show is pulled down by the width prior; a shallow one is covered by the prior's breadth),
so report it at more than one.
"""

from __future__ import annotations

import argparse
import json
import time

import numpy as np
import pandas as pd

from facelab.analysis.bayes_psychometric import posterior_fit
from facelab.analysis.psychometric import count_responses, fit_psychometric
from facelab.analysis.tasks import calibrate_design, choice_outcome
from facelab.experiment.simulate import design_sampler, simulated_rows
from facelab.protocol import load_protocol
from facelab.resources import protocol_path

ESTIMATORS = ("calibrated", "profile", "credible", "ml_bootstrap")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("protocol", nargs="?", default="gain_staircase")
    ap.add_argument("--observers", type=int, default=200)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--boot", type=int, default=200)
    ap.add_argument("--group", type=int, default=8, help="participants per study (calibrated)")
    ap.add_argument("--stop-after", type=int, help="every session stops after this many trials")
    ap.add_argument("--estimators", nargs="+", default=list(ESTIMATORS), choices=ESTIMATORS)
    for name in ("midpoint", "slope", "lapse"):
        ap.add_argument(f"--{name}", type=float, help=f"true {name} (default: the protocol's)")
    args = ap.parse_args()
    path = protocol_path(args.protocol) if not args.protocol.endswith(".yaml") else args.protocol
    protocol = load_protocol(path)
    names = ("midpoint", "slope", "lapse")
    changed = {k: getattr(args, k) for k in names if getattr(args, k) is not None}
    if changed:
        sim = protocol.simulation
        observer = sim.observer.model_copy(update=changed)
        protocol = protocol.model_copy(
            update={"simulation": sim.model_copy(update={"observer": observer})}
        )
    truth = protocol.simulation.observer
    task = protocol.tasks[0]
    master = np.random.default_rng(args.seed)
    found: dict[str, list[tuple[float, ...]]] = {name: [] for name in args.estimators}
    seconds = dict.fromkeys(args.estimators, 0.0)
    children = master.spawn(args.observers)
    observers = []  # (trials with y, counts, gamma) per observer
    for i, child in enumerate(children):
        rows = pd.DataFrame(simulated_rows(protocol, participant=f"S{i:04d}", rng=child))
        rows = rows[rows["item"] == task.id].sort_values("trial_index")
        if args.stop_after:
            rows = rows.iloc[: args.stop_after]
        y, gamma = choice_outcome(rows, task)
        trials = rows.assign(y=y.to_numpy())
        observers.append((trials, count_responses(trials, x="level", y="y"), gamma))
    sampler = design_sampler(protocol)
    drops = None
    for i, (_, counts, gamma) in enumerate(observers):
        if "calibrated" in args.estimators and i % args.group == 0:
            # a study of this observer and the next group - 1: calibrated on their answers
            t0 = time.perf_counter()
            study = pd.concat([t for t, _, _ in observers[i : i + args.group]], ignore_index=True)
            calibration = calibrate_design(
                study, task, gamma=gamma, sampler=sampler,
                rng=np.random.default_rng([args.seed, i]),
            )  # fmt: skip
            drops = calibration.drops() if calibration is not None else None
            seconds["calibrated"] += time.perf_counter() - t0
        child = children[i]
        for name in args.estimators:
            t0 = time.perf_counter()
            if name == "ml_bootstrap":
                ml = fit_psychometric(counts, gamma=gamma, n_boot=args.boot, rng=child)
                row = (ml.midpoint, ml.midpoint_ci_low, ml.midpoint_ci_high,
                       ml.beta, ml.beta_ci_low, ml.beta_ci_high)  # fmt: skip
            else:
                post = posterior_fit(
                    counts, gamma=gamma, interval="profile" if name == "calibrated" else name,
                    drops=drops if name == "calibrated" else None,
                )  # fmt: skip
                row = (post.midpoint, post.midpoint_ci_low, post.midpoint_ci_high,
                       post.slope, post.slope_ci_low, post.slope_ci_high)  # fmt: skip
            seconds[name] += time.perf_counter() - t0
            found[name].append(row)
    report = {"protocol": args.protocol, "observers": args.observers, "seed": args.seed,
              "stop_after": args.stop_after,
              "truth": {"midpoint": truth.midpoint, "slope": truth.slope, "lapse": truth.lapse,
                        "midpoint_sd": truth.midpoint_sd}}  # fmt: skip
    for name, values in found.items():
        a = np.array(values, dtype=float)
        mid_in = (a[:, 1] <= truth.midpoint) & (truth.midpoint <= a[:, 2])
        slope_in = (a[:, 4] <= truth.slope) & (truth.slope <= a[:, 5])
        report[name] = {
            "midpoint_coverage": round(float(np.mean(mid_in)), 3),
            "slope_coverage": round(float(np.mean(slope_in)), 3),
            "midpoint_median": round(float(np.nanmedian(a[:, 0])), 4),
            "slope_median": round(float(np.nanmedian(a[:, 3])), 2),
            "slope_ci_width_median": round(float(np.nanmedian(a[:, 5] - a[:, 4])), 2),
            "seconds_per_fit": round(seconds[name] / args.observers, 4),
        }
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
