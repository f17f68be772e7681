"""``facelab impression``: fit an impression model (seed 001), render its levels, or write the
synthetic expression database."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from facelab.errors import FacelabError
from facelab.experiment.cli.common import (
    AddCommand,
    GridProgress,
    check_options,
    cluster_of,
    cluster_options,
    force_option,
    output_dir,
    output_file,
    parse_size,
    real,
    say_checks,
    seed,
    verbs,
    whole,
)

__all__ = ["register"]


def _fit(args: argparse.Namespace) -> int:
    from facelab.stimuli.impression.model import (
        fit_impression,
        level_visibility,
        read_arkit_samples,
        read_vertex_samples,
    )

    if not args.label:
        raise FacelabError("facelab impression fit: --label COLUMN is required")
    if not args.out:
        raise FacelabError("facelab impression fit: --out MODEL.json is required")
    out = output_file(args.out, option="--out", force=args.force)
    samples = (
        read_arkit_samples(Path(args.input))
        if args.space == "arkit"
        else read_vertex_samples(Path(args.input))
    )
    model = fit_impression(
        samples,
        label=args.label,
        method=args.method,
        k=args.k,
        variance=args.variance,
        positive=args.positive,
        expressions=args.expression or None,
        orthogonal_to_speech=args.orthogonal_to_speech,
        svm_c=args.svm_c,
        step=args.step,
    )
    out.write_text(json.dumps(model.to_json(), indent=1) + "\n", encoding="utf-8")
    print(f"impression model '{args.label}' ({args.method}, {model.k_rule}) -> {out}")
    print(f"{'expression':<14} {'n':>4} {'K':>3} {'var':>6} {'delta':>8}  leave-one-person-out")
    for e, m in model.expressions.items():
        score = ", ".join(
            f"{k} {v}" for k, v in m.cv.items() if k in ("accuracy", "balanced_accuracy", "r2", "r")
        )
        print(
            f"{e:<14} {m.n:>4} {len(m.basis):>3} {m.cv.get('variance_explained', 0):>6.3f} "
            f"{m.delta:>8.4f}  {score}"
        )
    for line in level_visibility(model):
        print(line)
    return 0


def _render(args: argparse.Namespace) -> int:
    from facelab.stimuli.avatar import load
    from facelab.stimuli.checks.clip_set_checks import check_clip_set, impression_rows
    from facelab.stimuli.impression.model import ImpressionModel
    from facelab.stimuli.render.impression_clips import Timing, render_levels
    from facelab.stimuli.render.renderer import RenderSettings

    if not args.expression or len(args.expression) != 1:
        raise FacelabError("facelab impression render: give one --expression NAME")
    if not args.levels:
        raise FacelabError("facelab impression render: give --levels Q [Q ...]")
    if not args.out:
        raise FacelabError("facelab impression render: --out DIR is required")
    out = output_dir(args.out, option="--out")
    model = ImpressionModel.load(Path(args.input))
    size = parse_size(args.size) or (1280, 720)
    avatar = load(Path(args.avatar)) if args.avatar else None
    timing = Timing(
        lead_s=args.lead_s, onset_s=args.onset_s, hold_s=args.hold_s, offset_s=args.offset_s,
        ease=args.ease, k=args.k_ease,
    )  # fmt: skip
    progress = GridProgress(quiet=False, prefix="render")
    progress.start(len(args.levels))
    try:
        rows = render_levels(
            model,
            expression=args.expression[0],
            levels=args.levels,
            out=out,
            avatar=avatar,
            settings=RenderSettings(width=size[0], height=size[1], msaa=args.msaa),
            fps=args.fps,
            timing=timing,
            cluster=cluster_of(args),
            progress=progress,
        )
    finally:
        progress.close()
    for r in rows:
        print(
            f"{r['path']}: q {r['q_intended']:g} -> realised {r['q_realised']:.3f}, "
            f"decision {r['decision_value']:.3f}, {r['clipped_channels']} channels clipped"
        )
    print(f"wrote {len(rows)} clips, clips.csv, contact_{args.expression[0]}.png into {out}")
    report = check_clip_set(
        clips_dir=out, clips=rows, extra=impression_rows(rows), accept=args.accept_check,
        graded={args.expression[0]: [(float(r["q_intended"]), r["clip_id"]) for r in rows]},
    )  # fmt: skip
    say_checks(report)
    if report.failures:
        raise report.error()
    return 0


def _synth(args: argparse.Namespace) -> int:
    import numpy as np

    from facelab.stimuli.arkit import ARKIT_NAMES
    from facelab.stimuli.impression.synth import TRUE_DIRECTION, synthetic_samples

    if not args.out:
        raise FacelabError("facelab impression synth: --out SAMPLES.csv is required")
    out = output_file(args.out, option="--out", force=args.force)
    df = synthetic_samples(people=args.people, rng=np.random.default_rng(args.seed))
    df.to_csv(out, index=False)
    truth = out.with_suffix(".truth.json")
    truth.write_text(
        json.dumps(
            {
                "synthetic": True,
                "note": "SYNTHETIC database from facelab.stimuli.impression.synth - not people",
                "seed": args.seed,
                "people": args.people,
                "label": "friendly (high/low), friendly_rating (0-100)",
                "true_direction": {
                    n: round(float(v), 6) for n, v in zip(ARKIT_NAMES, TRUE_DIRECTION, strict=True)
                },
            },
            indent=1,
        )
        + "\n",
        encoding="utf-8",
    )
    print(f"wrote a SYNTHETIC database ({args.people} people x 8 expressions) to {out}; "
          f"its true direction to {truth}")  # fmt: skip
    return 0


def _samples(args: argparse.Namespace) -> int:
    import csv

    from facelab.stimuli.impression.model import samples_from_captures

    if not args.input or not args.out:
        raise FacelabError("facelab impression samples INDEX.csv --out SAMPLES.csv")
    out = output_file(args.out, option="--out", force=args.force)
    rows = samples_from_captures(Path(args.input), window_s=args.window, fps=args.capture_fps)
    with open(out, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"wrote {len(rows)} samples (one row per person and expression) to {out}")
    return 0


def _cmd_impression(args: argparse.Namespace) -> int:
    actions = {"fit": _fit, "render": _render, "synth": _synth, "samples": _samples}
    return actions[args.action](args)


def register(add: AddCommand) -> None:
    """Add this family's subcommands: one verb each, with its own options."""
    p = add(
        "impression",
        "impression stimuli (seed 001): fit a direction from labelled expression samples, "
        "render clips at levels along it, or write a synthetic database",
        _cmd_impression,
    )
    verb = verbs(p)
    v = verb("fit", "fit an impression model from labelled expression samples")
    v.add_argument("input", metavar="SAMPLES.csv", help="person, expression, labels…, 52 ARKit")
    v.add_argument("--label", required=True, metavar="COLUMN", help="the label column")
    v.add_argument("--space", choices=["arkit", "vertices"], default="arkit", help="sample space")
    v.add_argument("--k", type=whole(lo=1), help="PCA components (default: by --variance)")
    v.add_argument("--variance", type=real(above=0, hi=1), default=0.9,
                   help="variance to keep (default 0.9)")  # fmt: skip
    v.add_argument("--method", choices=["svm", "mean_diff", "ridge"], default="svm")
    v.add_argument("--svm-c", type=real(above=0), default=0.1, help="SVM C on RMS-scaled scores")
    v.add_argument("--positive", metavar="CLASS", help="the class the direction points to")
    v.add_argument("--orthogonal-to-speech", action="store_true",
                   help="keep the direction clear of the speech methods' mouth shapes")  # fmt: skip
    v.add_argument("--expression", action="append", metavar="NAME",
                   help="expressions to model (repeat; default all)")  # fmt: skip
    v.add_argument("--step", type=real(above=0), metavar="CHANGE",
                   help="choose delta so that q = 1 moves the channel that moves most by CHANGE "
                   "(ARKit units; metres for vertices; e.g. 0.25) instead of one SD of the "
                   "training projections")  # fmt: skip
    v.add_argument("--out", required=True, metavar="MODEL.json")
    force_option(v)

    v = verb("render", "one clip per level of an impression model, clips.csv, a contact sheet")
    v.add_argument("input", metavar="MODEL.json")
    check_options(v)
    v.add_argument("--expression", action="append", required=True, metavar="NAME",
                   help="the expression to play")  # fmt: skip
    v.add_argument("--levels", type=real(), nargs="+", required=True, metavar="Q",
                   help="levels q_c")  # fmt: skip
    v.add_argument("--size", metavar="WxH", help="default 1280x720")
    v.add_argument("--fps", type=whole(lo=1, hi=240), default=30)
    v.add_argument("--msaa", type=int, choices=[1, 2, 4, 8], default=4)
    v.add_argument("--avatar", metavar="FILE", help="an avatar file (default head)")
    v.add_argument("--lead-s", type=real(lo=0), default=0.3, help="neutral lead-in")
    v.add_argument("--onset-s", type=real(lo=0), default=0.6)
    v.add_argument("--hold-s", type=real(lo=0), default=1.2)
    v.add_argument("--offset-s", type=real(lo=0), default=0.6)
    v.add_argument("--ease", choices=["sigmoid", "linear", "smoothstep"], default="sigmoid")
    v.add_argument("--k-ease", type=real(above=0), default=5.0, help="sigmoid steepness (eq. 4)")
    v.add_argument("--out", required=True, metavar="DIR",
                   help="clip folder (clips of other levels already there are kept)")  # fmt: skip
    cluster_options(v)

    v = verb("synth", "a SYNTHETIC expression database with a known direction")
    v.add_argument("--people", type=whole(lo=2), default=40, help="people")
    v.add_argument("--seed", type=seed, default=1, help="seed of the database")
    v.add_argument("--out", required=True, metavar="SAMPLES.csv")
    force_option(v)

    v = verb("samples", "face captures (Live Link Face) reduced to one row per person and "
             "expression")  # fmt: skip
    v.add_argument("input", metavar="INDEX.csv",
                   help="person, expression, labels..., capture, time_s")  # fmt: skip
    v.add_argument("--window", type=real(above=0), default=0.1, help="seconds averaged")
    v.add_argument("--capture-fps", type=real(above=0), default=60.0,
                   help="the captures' Timecode frame rate")  # fmt: skip
    v.add_argument("--out", required=True, metavar="SAMPLES.csv")
    force_option(v)
