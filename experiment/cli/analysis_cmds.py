"""Analysis commands: ``analyze`` and ``power``."""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Callable
from pathlib import Path

from facelab.errors import AnalysisError, FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    cluster_of,
    cluster_options,
    deprecated,
    figure_suffixes,
    force_option,
    output_dir,
    output_file,
    parse_effects,
    protocol_argument,
    protocol_of,
    real,
    seed,
    whole,
)


def _cmd_analyze(args: argparse.Namespace) -> int:
    from facelab.analysis import run
    from facelab.analysis.pipeline import study_root
    from facelab.experiment.simulate import design_sampler
    from facelab.protocol import load_protocol

    protocol_file, results_dir = _analyze_paths(args)
    protocol = load_protocol(protocol_file)
    out = Path(args.out) if args.out else study_root(results_dir, protocol) / "analysis"
    if (out / "report.html").exists() and not args.force:
        raise FacelabError(
            f"{out} holds an analysis already; pass --force to replace it, or --out DIR"
        )
    done = run(
        results_dir,
        protocol,
        protocol_path=protocol_file,
        out=output_dir(out, option="--out"),
        method=args.method,
        exclude=args.exclude or (),
        accept_protocol_change=args.accept_protocol_change,
        clips=Path(args.clips) if args.clips else None,
        boot_seed=args.boot_seed,
        n_boot=args.bootstrap,
        max_dropped_frames=args.max_dropped_frames,
        max_av_offset_ms=args.max_av_offset_ms,
        sampler=design_sampler(protocol),
        exclude_rules=args.exclude_trials or (),
    )
    data, check = done.data, done.check
    kind = {"simulated": "SIMULATED ", "mixed": "MIXED (simulated and real) ", "unknown": ""}
    print(
        f"analysed {len(data)} {kind.get(check.provenance, '')}responses from "
        f"{data['participant'].nunique()} participants (primary procedure: {args.method})"
    )
    if check.provenance == "unknown":
        print("  provenance unknown: some sessions do not say whether they were simulated")
    for note in done.notes:
        print(f"  note: {note}")
    print_layout(done.results)
    _print_tasks(done.tasks)
    print(f"report: {done.files.html}\ntables and figures: {done.files.folder}")
    return 0


def _analyze_paths(args: argparse.Namespace) -> tuple[Path, Path]:
    """``analyze PROTOCOL RESULTS``; the old ``analyze RESULTS --protocol PROTOCOL`` too."""
    first, second = args.protocol, args.results
    if args.old_protocol:
        if second is not None:
            raise FacelabError(
                "give PROTOCOL RESULTS (or, the old spelling, RESULTS --protocol PROTOCOL)"
            )
        return Path(args.old_protocol), Path(first)
    if second is None:
        raise FacelabError("give the protocol and the results: facelab analyze PROTOCOL RESULTS")
    return Path(first), Path(second)


def print_layout(results: object, say: Callable[[str], None] = print) -> None:
    """The VAS tests, one line per item, stimulus set and procedure."""
    for row in results.layout.itertuples() if results is not None else ():
        if row.f != row.f:  # NaN: the test is not estimable; the reason is in the pairs column
            where = f"{row.item:>12} / {row.stimulus_set:<10} {row.procedure:>5}"
            say(f"  {where}: {row.pairs_p_lt_05}")
            continue
        reported = (
            ""
            if row.reported_anova_p != row.reported_anova_p  # NaN: the paper reports none
            else f" (paper: p = {row.reported_anova_p:.4f})"
        )
        say(
            f"  {row.item:>12} / {row.stimulus_set:<10} {row.procedure:>5}: "
            f"F({row.df1:g},{row.df2:g}) = {row.f:7.3f}, p = {row.anova_p:.4f}; "
            f"pairs p<.05: {row.pairs_p_lt_05}{reported}"
        )


def _print_tasks(tasks: object) -> None:
    tables = getattr(tasks, "tables", {})
    fits = tables.get("psychometric_fits")
    if fits is not None:
        for r in fits[fits["participant"] == "pooled"].itertuples():
            print(
                f"  {r.task:>12} psychometric (pooled, gamma {r.gamma:g}): midpoint "
                f"{r.midpoint:.3f} [{r.midpoint_ci_low:.3f}, {r.midpoint_ci_high:.3f}], "
                f"slope {r.slope:.3g}, lapse {r.lapse:.3f}, deviance {r.deviance:.2f} "
                f"(df {r.deviance_df})"
            )
        noted = fits[fits["note"].fillna("").astype(str) != ""]
        for (task, note), part in noted.groupby(["task", "note"], sort=False):
            print(f"  {task:>12} {', '.join(map(str, part['participant']))}: {note}")
    stairs = tables.get("staircase_thresholds")
    if stairs is not None:
        for (block, estimate), part in stairs.groupby(["block", "estimate"], sort=False):
            noted = part["note"].fillna("").astype(str).ne("")
            fine = part[~noted & part["threshold"].notna()]
            median = f"{fine['threshold'].median():.3f}" if len(fine) else "none"
            print(f"  staircase {block} ({estimate}): median threshold {median} over "
                  f"{len(fine)} of {len(part)} participants")  # fmt: skip
            for r in part[noted].itertuples():
                print(f"    {r.participant}: {r.note}")
    ident = tables.get("identification_summary")
    if ident is not None:
        for r in ident[ident["participant"] == "pooled"].itertuples():
            print(
                f"  {r.task:>12} identification (pooled): accuracy {r.accuracy:.3f} "
                f"(chance {r.chance:.3f}), kappa {r.kappa:.3f}, n = {r.n}"
            )
    by_condition = tables.get("identification_by_condition")
    if by_condition is not None:
        for r in by_condition.itertuples():
            print(
                f"  {r.task:>12} identification in {r.condition}: accuracy {r.accuracy:.3f}, "
                f"kappa {r.kappa:.3f}, n = {r.n}"
            )
    model = tables.get("identification_condition_model")
    if model is not None:
        for r in model[model["term"].str.startswith("C(")].itertuples():
            # C(condition)[T.composite] with note "reference: gestures_only; ..."
            level = r.term.split("[T.", 1)[-1].rstrip("]")
            reference = r.note.split(";")[0].removeprefix("reference: ")
            print(
                f"  {r.task:>12} correct in {level} vs {reference}: odds ratio "
                f"{r.odds_ratio:.2f} [{r.or_ci_low:.2f}, {r.or_ci_high:.2f}], "
                f"t({r.df:g}) = {r.t:.2f}, p = {r.p:.4f}"
            )
    trend = tables.get("trend_contrast")
    if trend is not None:
        for r in trend.itertuples():
            print(
                f"  {r.item:>12} / {r.stimulus_set:<10} linear trend: slope {r.slope:.3g} "
                f"per level unit, F(1,{r.df}) = {r.f:.3f}, p = {r.p:.4f}"
            )
    lmm = tables.get("graded_lmm")
    if lmm is not None:
        for r in lmm.itertuples():
            print(
                f"  {r.item:>12} / {r.stimulus_set:<10} mixed model: slope {r.slope:.3g} "
                f"(SE {r.slope_se:.3g}), t({r.df}) = {r.t:.3f}, p = {r.p:.4f}, slope SD between "
                f"participants {r.sd_slope:.3g}"
            )


def _cmd_power(args: argparse.Namespace) -> int:
    import json

    import numpy as np

    from facelab.analysis import power

    if args.simulate is not None:
        return _simulated_power(args)
    if args.plot:
        raise FacelabError("--plot draws the power of simulated studies against n: it goes with "
                           "--simulate")  # fmt: skip
    args.sims = 4000 if args.sims is None else args.sims
    rows: list[dict[str, object]] = []
    assumptions = ""
    if args.pilot:
        from facelab.analysis.load import load_results
        from facelab.protocol import load_protocol

        protocol_file = protocol_of(args)
        if not protocol_file:
            raise FacelabError("--pilot needs the PROTOCOL (for the study id and conditions)")
        protocol = load_protocol(protocol_file)
        data = load_results(args.pilot, study=protocol.study.id)
        n_pilot = data["participant"].nunique()
        effect = power.f2_from_pilot if n_pilot >= 2 else power.f2_from_one
        for item in protocol.items:
            for sset in protocol.stimulus_sets:
                sub = data[(data["item"] == item.id) & (data["stimulus_set"] == sset.id)]
                if not sub.empty:
                    try:
                        found = effect(sub)
                    except AnalysisError as exc:  # this item says nothing; the others may
                        found = {"not_estimable": str(exc)}
                    rows.append({"label": f"{item.id}/{sset.id}", **found})
        assumptions = (
            "effect sizes from pilot data (participant means, bias-corrected)"
            if n_pilot >= 2
            else "effect sizes from ONE participant: the error of a condition mean comes from "
            "their repeated ratings of each condition, without the participant x condition "
            "interaction that 2 or more people show - f2 is an upper bound, power and n "
            "optimistic, and one person's f2 varies widely (0 to 8 across five simulated "
            "one-person pilots of kato2021 whose 8-person f2 is 0.36-0.61); run a second "
            "pilot participant before planning on these"
        )
        tasks = ", ".join(t.id for t in protocol.tasks)
        simulate_hint = (
            f"for its forced-choice and identification tasks ({tasks}) put the pilot's effects "
            f"in the protocol's simulation section and run: facelab power {protocol_file} "
            "--simulate"
        )
        if not rows:
            raise FacelabError(
                f"--pilot {args.pilot}: no VAS ratings (study {protocol.study.id!r}); --pilot "
                "powers the repeated-measures ANOVA of VAS ratings"
                + (f"; {simulate_hint}" if tasks else "")
            )
        if all("not_estimable" in r for r in rows):
            raise FacelabError(f"--pilot {args.pilot}: no item gives an effect size - "
                               + "; ".join(f"{r['label']}: {r['not_estimable']}"
                                           for r in rows))  # fmt: skip
        if tasks:
            assumptions += f"; VAS items only - {simulate_hint}"
    elif args.reported_p is not None:
        bad = [p for p in args.reported_p if not 0 < p < 1]
        if bad:
            raise FacelabError(f"--reported-p {bad[0]:g}: a p-value lies strictly between 0 and 1")
        for p in args.reported_p:
            est = power.f2_from_reported_p(
                p=p,
                participants=args.reported_n,
                conditions=args.conditions,
                reps=args.reps,
                icc=args.icc,
                interaction_share=args.interaction_share,
            )
            rows.append({"label": f"reported p={p:g}", "k": args.conditions, **est})
        assumptions = (
            "from the paper procedure's p (pooled one-way ANOVA, "
            f"{args.reported_n} participants x "
            f"{args.conditions} conditions x {args.reps} ratings); assumed variance split: "
            f"participant {args.icc:g}, participant x condition {args.interaction_share:g}, "
            f"rating noise {1 - args.icc - args.interaction_share:g}"
        )
    else:
        raise FacelabError("give --reported-p P [P ...] (with the design) or --pilot RESULTS")
    rng = np.random.default_rng(args.sim_seed)
    for row in rows:
        if "not_estimable" in row:
            continue
        k = int(row.get("k", args.conditions))
        n_needed = power.participants_needed(
            k=k, f2=float(row["f2_rm"]), power=args.power, alpha=args.alpha
        )
        row["k"] = k
        row["power_at_n"] = power.rm_power(
            n=args.reported_n, k=k, f2=float(row["f2_rm"]), alpha=args.alpha
        )
        row["n_needed"] = n_needed
        row["simulated_power_at_needed"] = (
            power.simulate_power(
                n=n_needed, k=k, f2=float(row["f2_rm"]), alpha=args.alpha, sims=args.sims, rng=rng
            )
            if n_needed
            else None
        )
    if args.json:
        print(
            json.dumps(
                {
                    "assumptions": assumptions,
                    "alpha": args.alpha,
                    "target_power": args.power,
                    "n": args.reported_n,
                    "rows": rows,
                },
                indent=2,
            )
        )
        return 0
    print(
        f"power of the repeated-measures ANOVA on participant means (alpha {args.alpha:g}); "
        f"{assumptions}"
    )
    for row in rows:
        if "not_estimable" in row:
            print(f"  {row['label']}: not estimable - {row['not_estimable']}")
            continue
        extra = (
            f", pilot F {row['f_pilot']:.2f}"
            if "f_pilot" in row
            else (f", implied F {row['f']:.2f}, eta_p^2 {row['eta_p_sq']:.3f}")
        )
        if float(row["f2_rm"]) <= 0:
            need = (
                "cannot be computed - the implied effect is zero (F <= 1): this p gives no "
                "evidence of any difference to power a study for"
            )
        else:
            need = row["n_needed"] if row["n_needed"] else "> 10000"
        sim = row["simulated_power_at_needed"]
        sim_text = f" (simulated: {sim:.3f} over {args.sims} runs)" if sim is not None else ""
        print(
            f"  {row['label']}: f2_rm {float(row['f2_rm']):.3f}{extra}; power with "
            f"n={args.reported_n}: {float(row['power_at_n']):.3f}; n for "
            f"{args.power:g} power: {need}{sim_text}"
        )
    return 0


def _simulated_power(args: argparse.Namespace) -> int:
    """``facelab power PROTOCOL --simulate``: every test's power and every threshold's
    precision at each n, by simulation."""
    import json

    import numpy as np

    from facelab.experiment.simulated_power import simulated_power
    from facelab.protocol import load_protocol

    if args.pilot or args.reported_p is not None:
        raise FacelabError("--simulate takes the protocol's simulation section as the truth; "
                           "leave out --pilot and --reported-p")  # fmt: skip
    if not 0 < args.power < 1:
        raise FacelabError(f"--power {args.power:g}: a target power lies strictly between 0 and 1")
    plot = (output_file(args.plot, option="--plot", force=args.force, suffixes=figure_suffixes)
            if args.plot else None)  # fmt: skip
    protocol_file = args.simulate if isinstance(args.simulate, str) else protocol_of(args)
    if isinstance(args.simulate, str):
        print(
            "facelab power: --simulate PROTOCOL is deprecated; use facelab power PROTOCOL "
            "--simulate (the old spelling works for this release)",
            file=sys.stderr,
        )
    if not protocol_file:
        raise FacelabError("--simulate needs the PROTOCOL: facelab power PROTOCOL --simulate")
    protocol = load_protocol(protocol_file)
    effects = {**protocol.simulation.effects, **(parse_effects(args.effect) or {})}
    n_values = sorted(set(args.n or (8, 12, 16, 24, 32)))
    sims = 200 if args.sims is None else args.sims

    def progress(n: int, seconds: float) -> None:
        print(f"  n={n}: {sims} studies simulated and analysed in {seconds:.1f} s",
              file=sys.stderr, flush=True)  # fmt: skip

    result = simulated_power(
        protocol, n_values=n_values, sims=sims, rng=np.random.default_rng(args.sim_seed),
        alpha=args.alpha, effects=effects, progress=progress, jobs=args.jobs,
        cluster=cluster_of(args),
    )  # fmt: skip
    table = result.power
    if plot is not None and not table.empty:
        from facelab.analysis import figures

        fig = figures.power_figure(
            table,
            target=args.power,
            alpha=args.alpha,
            title=f"{protocol.study.id}: power by simulation ({sims} studies per n)",
        )
        fig.savefig(plot)  # the format from the suffix: .png, .svg, .pdf
        import matplotlib.pyplot as plt

        plt.close(fig)
    needed = {}
    for (test, kind), part in table.groupby(["test", "kind"], sort=False):
        enough = part[part["power"] >= args.power]
        needed[(test, kind)] = int(enough["n"].min()) if not enough.empty else None
    sim = protocol.simulation
    truth = {
        "effects": effects,
        "model": sim.model.model_dump(),
        "identifier": sim.identifier.model_dump(),
        "observer": sim.observer.model_dump(),
    }
    if args.json:
        print(
            json.dumps(
                {
                    "protocol": str(protocol_file),
                    "assumptions": truth,
                    "alpha": args.alpha,
                    "target_power": args.power,
                    "sims": sims,
                    "seed": args.sim_seed,
                    "rows": table.to_dict(orient="records"),
                    "n_needed": [{"test": t, "kind": k, "n": n} for (t, k), n in needed.items()],
                    "precision": result.precision.to_dict(orient="records"),
                },
                indent=2,
            )
        )
        return 0
    print(
        f"simulation of {protocol.study.id!r}: {sims} studies per n; truth = the protocol's "
        f"simulation section"
    )
    head = "".join(f"{f'n={n}':>8}" for n in n_values)
    if not table.empty:
        print(f"power (alpha {args.alpha:g}); VAS effects {effects}")
        print(f"  {'test':<44}{'kind':<16}{head}  n for {args.power:g}")
        for (test, kind), part in table.groupby(["test", "kind"], sort=False):
            cells = "".join(f"{'n/a':>8}" if r.failed >= r.sims else f"{r.power:8.2f}"
                            for r in part.sort_values("n").itertuples())  # none could run
            n = needed[(test, kind)]
            print(f"  {test:<44}{kind:<16}{cells}  {n if n else f'> {n_values[-1]}'}")
        print(f"  Monte Carlo SE of a power p: sqrt(p (1 - p) / {sims}) "
              f"(at most {0.5 / sims**0.5:.3f})")  # fmt: skip
    precision = result.precision
    if not precision.empty:
        if precision["estimate"].str.endswith(" midpoint").any():
            print(
                f"precision of the pooled psychometric midpoint (true midpoint "
                f"{sim.observer.midpoint:g}, slope {sim.observer.slope:g}, participants' SD "
                f"{sim.observer.midpoint_sd:g}): SD across studies (RMSE)"
            )
        if precision["estimate"].str.endswith(("srt_db", "benefit_db")).any():
            print("precision of the mean SRT and benefit per condition series (truths: the "
                  "protocol's simulation.srt): SD across studies (RMSE), dB")  # fmt: skip
        if precision["estimate"].str.endswith(("pss_ms", "width_ms")).any():
            print("precision of the mean window per condition series (truths: the protocol's "
                  "simulation.timing): SD across studies (RMSE), ms")  # fmt: skip
        print(f"  {'estimate':<60}{head}")
        for name, part in precision.groupby("estimate", sort=False):
            part = part.sort_values("n")
            cells = "".join(f"{r.sd:8.3f}" for r in part.itertuples())
            rmse = "".join(f"{f'({r.rmse:.3f})':>8}" for r in part.itertuples())
            print(f"  {name:<60}{cells}\n  {'':<60}{rmse}")
    for frame in (table, precision):
        for r in frame[frame["failed"] > 0].itertuples():
            label = getattr(r, "test", None) or r.estimate
            none = (" - n/a: no simulated study could be analysed this way (e.g. too few "
                    "participants for the test)" if r.failed >= r.sims else "")  # fmt: skip
            print(f"  note: {label}, n={r.n}: {r.failed} of {r.sims} fits failed{none}")
    return 0


def register(add: AddCommand) -> None:
    """Add this family's subcommands."""
    p = add("analyze", "analyse session logs into tables, figures and a report", _cmd_analyze)
    p.add_argument("protocol", metavar="PROTOCOL", help="the study's protocol YAML")
    p.add_argument(
        "results", nargs="?", metavar="RESULTS", help="results root or the study's folder"
    )
    deprecated(p, "--protocol", new="facelab analyze PROTOCOL RESULTS", dest="old_protocol")
    p.add_argument(
        "--method",
        choices=["rm", "paper"],
        default="rm",
        help="primary procedure: rm (sound, default) or paper (pooled ANOVA + Tukey)",
    )
    p.add_argument("--exclude", action="append", metavar="ID", help="leave out a participant")
    p.add_argument(
        "--clips",
        metavar="DIR",
        help="rendered clips with behaviour logs, for the behaviour covariates "
        "(default: <results>/<study>/clips)",
    )
    p.add_argument(
        "--bootstrap",
        type=whole(lo=0),
        default=200,
        metavar="N",
        help="parametric-bootstrap resamples for psychometric CIs (default 200; 0: none)",
    )
    p.add_argument(
        "--boot-seed", type=seed, default=1, help="seed of the bootstrap generator (default 1)"
    )
    deprecated(p, "--seed", new="--boot-seed", dest="boot_seed", type=seed)
    p.add_argument(
        "--accept-protocol-change",
        action="store_true",
        help="analyse sessions that ran another version of the protocol file (reported)",
    )
    p.add_argument(
        "--out", metavar="DIR", help="output folder (default <results>/<study>/analysis)"
    )
    p.add_argument(
        "--max-dropped-frames",
        type=whole(lo=0),
        metavar="N",
        help="leave out responses to trials whose clip dropped more than N frames (the report "
        "says how many per condition; default: keep all, and table the drops)",
    )
    p.add_argument(
        "--max-av-offset-ms",
        type=_milliseconds,
        metavar="MS",
        help="leave out responses to trials drawn live (display live3d/webxr) whose picture and "
        "sound were more than MS apart (av_offset_ms of the playback record; the report says "
        "how many per condition; default: keep all, and table the live measures)",
    )
    p.add_argument(
        "--exclude-trials",
        action="append",
        metavar="RULE",
        help="leave out responses to trials whose playback record meets RULE, a measure, a "
        "comparison and a number (repeatable): e.g. \"head_yaw_range_deg > 30\", "
        "\"frame_age_max_ms > 100\", \"avatar_distance_m < 0.8\", \"dropped > 2\"; the "
        "report says how many per condition and rule",
    )
    force_option(p)

    p = add(
        "power",
        "implied effect size and participants needed for a chosen power (RM analysis)",
        _cmd_power,
    )
    p.add_argument(
        "--reported-p",
        type=real(),
        nargs="+",
        metavar="P",
        help="p-value(s) reported for the paper's pooled one-way ANOVA",
    )
    protocol_argument(p, optional=True)
    p.add_argument("--pilot", metavar="RESULTS", help="pilot session logs instead of a p-value")
    p.add_argument(
        "--reported-n",
        type=whole(lo=2),
        default=8,
        metavar="N",
        help="participants of the reported study (and n for 'power at n')",
    )
    deprecated(p, "--participants", new="--reported-n", dest="reported_n", type=whole(lo=2))
    p.add_argument("--conditions", type=whole(lo=2), default=3, metavar="K")
    p.add_argument(
        "--reps",
        type=whole(lo=1),
        default=2,
        metavar="R",
        help="ratings per participant x condition",
    )
    p.add_argument(
        "--icc", type=real(lo=0, below=1), default=0.3, help="assumed participant share of variance"
    )
    p.add_argument(
        "--interaction-share",
        type=real(lo=0, below=1),
        default=0.1,
        help="assumed participant x condition share of variance",
    )
    p.add_argument("--power", type=real(above=0, below=1), default=0.8, help="target power")
    p.add_argument("--alpha", type=real(above=0, below=1), default=0.05)
    p.add_argument(
        "--simulate",
        nargs="?",
        const=True,
        default=None,
        metavar="PROTOCOL",
        help="power of every test of PROTOCOL by simulating whole studies in memory, with its "
        "simulation section as the truth (any design: VAS, identification, graded); "
        "--simulate PROTOCOL is the old spelling",
    )
    p.add_argument(
        "--n",
        type=whole(lo=1, hi=5000),
        nargs="+",
        metavar="N",
        help="with --simulate: numbers of participants to try (default 8 12 16 24 32)",
    )
    p.add_argument(
        "--plot", metavar="PNG", help="with --simulate: power against n, one line per test"
    )
    p.add_argument(
        "--effect",
        action="append",
        metavar="COND=POINTS",
        help="with --simulate: a condition's VAS effect in points, replacing the protocol's "
        "for that condition (repeatable)",
    )
    p.add_argument(
        "--jobs",
        type=whole(lo=1),
        default=os.cpu_count() or 1,
        metavar="J",
        help="with --simulate: processes to simulate in (default: one per CPU); the result "
        "does not depend on it",
    )
    cluster_options(p, what="simulated studies (with --simulate; instead of --jobs)")
    p.add_argument(
        "--sims",
        type=whole(lo=1, hi=1_000_000),
        metavar="S",
        help="Monte Carlo runs: of the formula check (default 4000), or per n with "
        "--simulate (default 200)",
    )
    p.add_argument("--sim-seed", type=seed, default=1, help="seed of the Monte Carlo runs")
    deprecated(p, "--seed", new="--sim-seed", dest="sim_seed", type=seed)
    force_option(p)
    p.add_argument("--json", action="store_true", help="print JSON")

    p = add("score-typed", "score typed answers against what was said, as pronounced "
            "(morae and keywords)", _cmd_score_typed)  # fmt: skip
    p.add_argument("answers", metavar="CSV", help="columns target, response [, keywords]")
    p.add_argument("--strict", action="store_true",
                   help="a keyword counts only when every mora is right (default: one wrong "
                   "mora allowed in keywords of three or more)")  # fmt: skip
    p.add_argument("--out", metavar="CSV", help="write the scored table here (default: stdout)")
    force_option(p)


def _cmd_score_typed(args: argparse.Namespace) -> int:
    """Score typed answers against what was said (as pronounced: kana and kanji variants,
    long vowels; morae and keywords)."""
    import pandas as pd

    from facelab.analysis.typed_scoring import score_table
    from facelab.japanese_reading import first_unsaid_keyword, morae, pronunciation
    from facelab.textfiles import read_rows

    path = Path(args.answers)
    rows = read_rows(
        path, required=("target", "response"), error=FacelabError,
        expected="target, response and optionally keywords (space-separated)",
    )  # fmt: skip
    for line, row in rows.located():
        target = row["target"].strip()
        if not target:
            raise FacelabError(f"{path}:{line}: the target (what was said) is empty")
        said = morae(pronunciation(target))
        if not said:
            raise FacelabError(f"{path}:{line}: the target {target!r} has nothing to pronounce "
                               "(no mora to score)")  # fmt: skip
        word = first_unsaid_keyword(target, (row.get("keywords") or "").split())
        if word is not None:  # it would score 0 even in an answer that repeats the target
            raise FacelabError(
                f"{path}:{line}: keyword {word!r} is not said in the target {target!r} after "
                f"the keywords before it (read {''.join(said)}): keywords are words of what "
                "was said, in order, separated by spaces"
            )
    pairs = pd.DataFrame(list(rows), columns=rows.header, dtype=str)
    table = score_table(pairs, reader=pronunciation, split=morae, tolerant=not args.strict)
    if args.out:
        out = output_file(args.out, option="--out", force=args.force)
        table.to_csv(out, index=False)
        print(f"wrote {len(table)} scored answers to {out}", file=sys.stderr)
    else:
        table.to_csv(sys.stdout, index=False, lineterminator="\n")
    return 0


def _milliseconds(text: str) -> float:
    """A finite, non-negative number of milliseconds (for --max-av-offset-ms)."""
    import argparse
    import math

    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value) or value < 0:
        raise argparse.ArgumentTypeError(f"expected milliseconds >= 0, got {text!r}")
    return value
