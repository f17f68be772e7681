"""Writes an analysis folder: CSV tables, figures (PNG + SVG), report.html and report.md.

The report states the design, the sample (and whether it is simulated), the headline table
in the paper's layout - facelab's sound analysis, facelab's run of the paper's procedure,
and the paper's reported values side by side - the figures, and every detailed table.
"""

from __future__ import annotations

import base64
import datetime as dt
import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import jinja2
import numpy as np
import pandas as pd

import facelab.analysis.figures as figures
import facelab.analysis.srt as srt
import facelab.analysis.timing as timing
from facelab.analysis.integrity import DataCheck, check_data
from facelab.analysis.load import session_summary
from facelab.analysis.stimulus_checks import StimulusCheckSummary
from facelab.analysis.study import METHODS, StudyResults, bracket_pairs
from facelab.analysis.tasks import TaskResults
from facelab.protocol import Protocol

__all__ = ["ReportFiles", "write_report"]


@dataclass(frozen=True)
class ReportFiles:
    folder: Path
    html: Path
    markdown: Path
    tables: dict[str, Path]
    figures: list[Path]


def _text(localized: dict[str, str], language: str) -> str:
    return localized.get(language) or localized.get("en") or next(iter(localized.values()))


def _fmt(value: object) -> str:
    if isinstance(value, float):
        if value != value:  # NaN
            return ""
        return f"{value:.4g}" if abs(value) >= 1e-4 or value == 0 else f"{value:.2e}"
    return str(value)


def _html_table(frame: pd.DataFrame) -> str:
    """The table as HTML; pandas escapes every cell (the template marks it ``safe``)."""
    if len(frame.columns) == 0:  # e.g. the items of a protocol without VAS items
        return ""
    return frame.astype(object).map(_fmt).to_html(index=False, border=0, escape=True)


def _md_table(frame: pd.DataFrame) -> str:
    if len(frame.columns) == 0:
        return ""
    lines = ["| " + " | ".join(map(str, frame.columns)) + " |", "|" + "---|" * len(frame.columns)]
    lines += [
        "| " + " | ".join(_fmt(v).replace("|", "/") for v in row) + " |"
        for row in frame.itertuples(index=False)
    ]
    return "\n".join(lines)


@functools.cache
def _environment() -> jinja2.Environment:
    env = jinja2.Environment(
        loader=jinja2.PackageLoader("facelab.analysis", "templates"),
        autoescape=jinja2.select_autoescape(enabled_extensions=("html.j2",)),
        undefined=jinja2.StrictUndefined,
        keep_trailing_newline=True,
        trim_blocks=True,
    )
    env.filters["html_table"] = _html_table
    env.filters["md_table"] = _md_table
    return env


def _template(name: str) -> jinja2.Template:
    return _environment().get_template(name)


def _f_df(row: Any) -> str:
    """``F (df1, df2)``, or "not estimable" for a test a pilot's data cannot give."""
    if row.f != row.f:  # NaN
        return "not estimable"
    return f"{row.f:.3f} ({row.df1:g}, {row.df2:g})"


def _headline(results: StudyResults) -> pd.DataFrame:
    lay = results.layout
    rows = []
    for (item, sset), group in lay.groupby(["item", "stimulus_set"], sort=False):
        rm = group[group.procedure == "rm"].iloc[0]
        pa = group[group.procedure == "paper"].iloc[0]
        rows.append(
            {
                "item": item,
                "stimulus set": sset,
                "n": int(rm.n_participants),
                "facelab RM: F (df)": _f_df(rm),
                "facelab RM: p (GG)": rm.anova_p,
                "facelab RM: pairs (Holm)": rm.pairs_p_lt_05,
                "paper procedure: F (df)": _f_df(pa),
                "paper procedure: p": pa.anova_p,
                "paper procedure: pairs (Tukey)": pa.pairs_p_lt_05,
                "paper reported: p": rm.reported_anova_p,
                "paper reported: pairs": rm.reported_pairs,
            }
        )
    return pd.DataFrame(rows)


def write_report(
    *,
    results: StudyResults | None,
    data: pd.DataFrame,
    protocol: Protocol,
    out: Path,
    protocol_path: Path,
    check: DataCheck | None = None,
    tasks: TaskResults | None = None,
    stimulus_checks: StimulusCheckSummary | None = None,
) -> ReportFiles:
    """Write everything into ``out`` (created if needed; files in it are replaced).

    ``check`` (from :func:`facelab.analysis.integrity.check_data`) gives the banner, the
    data-check notes and the per-session table; without it they are derived from ``data``.
    ``stimulus_checks`` (the clips' ``stimulus_checks.csv``, summarised) is its own section.
    The HTML and Markdown are rendered from the templates in ``analysis/templates``.
    """
    if check is None:
        check = check_data(data, protocol, protocol_sha256=None, accept_protocol_change=True)
    out.mkdir(parents=True, exist_ok=True)
    tables: dict[str, Path] = {}
    all_tables = {**(results.tables() if results else {}), **(tasks.tables if tasks else {})}
    for name, frame in all_tables.items():
        tables[name] = out / f"{name}.csv"
        frame.to_csv(tables[name], index=False)

    language = protocol.presentation.language if figures.cjk_font() else "en"
    cond_ids = [c.id for c in protocol.conditions]
    cond_labels = [_text(c.label, language) for c in protocol.conditions]
    simulated = check.provenance == "simulated"
    figure_paths: list[Path] = []
    fig_blocks: list[tuple[str, Path]] = []
    proc = (
        "paired t-tests, Holm"
        if results is None or results.method == "rm"
        else "Tukey HSD on pooled ratings"
    )
    for item in protocol.items if results is not None else []:
        for sset in protocol.stimulus_sets:
            cells = results.cells[
                (results.cells["item"] == item.id) & (results.cells["stimulus_set"] == sset.id)
            ]
            if cells.empty:
                continue
            seen = set(cells["condition"])  # a set may be shown under some conditions only
            shown = [(c, lab) for c, lab in zip(cond_ids, cond_labels, strict=True) if c in seen]
            fig = figures.rating_figure(
                cells,
                conditions=[c for c, _ in shown],
                labels=[lab for _, lab in shown],
                brackets=bracket_pairs(results, item=item.id, stimulus_set=sset.id),
                title=f"{_text(item.question, language)} [{sset.id}]",
                ylabel="VAS (0-100)",
                scale=(item.range[0], item.range[1]),
                caption=(
                    f"0 = {_text(item.left_anchor, language)}, "
                    f"100 = {_text(item.right_anchor, language)}\n"
                    f"Boxes: participant means (n = {cells['participant'].nunique()}); "
                    f"brackets: p < .05, {proc}." + ("  SIMULATED DATA" if simulated else "")
                ),
            )
            paths = figures.save(fig, out / f"fig_{item.id}_{sset.id}")
            figure_paths += paths
            fig_blocks.append((f"{item.id} / {sset.id}", paths[0]))

    if tasks is not None:
        task_blocks = _task_figures(tasks, protocol, out, language, simulated)
        fig_blocks += task_blocks
        figure_paths += [f for _, png in task_blocks for f in (png, png.with_suffix(".svg"))]
    headline = _headline(results) if results is not None else pd.DataFrame()
    sessions = session_summary(data).merge(
        check.sessions[["participant", "session", "expected", "complete", "protocol_matches"]],
        on=["participant", "session"],
        how="left",
    )
    notes = [*check.notes, *(results.notes if results else ()), *(tasks.notes if tasks else ())]
    design = pd.DataFrame(
        [
            {
                "block": b.id,
                "stimulus set": b.stimulus_set,
                "sets": b.sets,
                "per condition per set": b.presentations_per_condition,
                "order": b.order,
                "task": b.task or "VAS items",
                "design": b.design,
                # the blocks' order: the protocol's, or a Latin-square row per participant
                "block order": protocol.presentation.block_order.replace("_", " "),
            }
            for b in protocol.blocks
        ]
    )
    conditions = pd.DataFrame(
        [
            {
                "condition": c.id,
                "label": _text(c.label, language),
                "method": c.method,
                "params": ", ".join(f"{k}={v}" for k, v in c.params.items()),
            }
            for c in protocol.conditions
        ]
    )
    items = pd.DataFrame(
        [
            {
                "item": i.id,
                "question": _text(i.question, language),
                "left (0)": _text(i.left_anchor, language),
                "right (100)": _text(i.right_anchor, language),
            }
            for i in protocol.items
        ]
    )
    details = (
        {}
        if results is None
        else {
            "Repeated-measures ANOVA on participant means": results.rm_anova,
            "Paired t-tests on participant means (Holm)": results.pairwise,
            "Friedman test on participant means": results.friedman,
            "Linear mixed model on all ratings (F with the aggregated df)": results.lmm,
            "Paper's procedure: one-way ANOVA on pooled ratings": results.paper_anova,
            "Paper's procedure: Tukey HSD on pooled ratings (diff = mean(b) - mean(a))": (
                results.paper_tukey
            ),
        }
    )
    for name, frame in (tasks.tables if tasks else {}).items():
        details[_TASK_HEADINGS.get(name, name)] = frame
    banner = check.banner
    reported = protocol.reported_results
    when = dt.datetime.now(dt.UTC).strftime("%Y-%m-%d %H:%M UTC")
    title = f"facelab report - {protocol.study.title}"
    method_note = (
        ""
        if results is None
        else (
            f"Primary procedure: {METHODS[results.method]}. The table shows both: the sound "
            "within-subject analysis (participant means, n = participants) and the paper's "
            "procedure, which pools every rating as if independent (pseudo-replication: error df "
            "count ratings, not people) and is shown only for replication."
        )
    )

    context = {
        "title": title,
        "css": _CSS,
        "protocol": protocol,
        "protocol_path": str(protocol_path),
        "when": when,
        "banner": banner,
        "notes": notes,
        "headline": headline if results is not None else None,
        "method_note": method_note,
        "reported": reported,
        "task_headline": _task_headline(tasks),
        "stimulus_checks": stimulus_checks,
        "figures": [
            {
                "label": label,
                "png": png.name,
                "svg": png.with_suffix(".svg").name,
                "data": base64.b64encode(png.read_bytes()).decode("ascii"),
            }
            for label, png in fig_blocks
        ],
        "conditions": conditions,
        "design": design,
        "items": items,
        "sessions": sessions,
        "details": list(details.items()),
        "csv_files": [p.name for p in tables.values()],
    }
    html_path = out / "report.html"
    html_path.write_text(_template("report.html.j2").render(context), encoding="utf-8")
    md_path = out / "report.md"
    md_path.write_text(_template("report.md.j2").render(context), encoding="utf-8")
    return ReportFiles(
        folder=out, html=html_path, markdown=md_path, tables=tables, figures=figure_paths
    )


_TASK_HEADINGS = {
    "ssq_summary": "Simulator sickness (SSQ, Kennedy et al. 1993): nausea N, oculomotor O, "
    "disorientation D and total scores per moment, and their change within participants "
    "(n participants; mean with 95 % t interval, median and quartiles; Wilcoxon signed-rank p "
    "for the change)",
    "ssq": "Simulator sickness: every questionnaire's scores (weights N 9.54, O 7.58, "
    "D 13.92, total 3.74 on the raw sums)",
    "ssq_symptoms": "Simulator sickness: each symptom's answers per moment",
    "vr_screen_poses_summary": "VR screens: how participants moved while each kind of "
    "screen waited for their answer (median seconds, head yaw range deg, head travel m, "
    "controller path m)",
    "vr_screen_poses": "VR screens: per screen shown in VR, the head's yaw, pitch and roll "
    "ranges (deg), its travel (m) and the controllers' path (m)",
    "conversation_summary": "Live conversation: each item asked about the partner after it "
    "(n participants; mean with 95 % t interval, median and quartiles)",
    "conversation": "Live conversation: per session how it ended, how long it lasted, the "
    "turns, and the ratings of the partner",
    "pilot_sessions": "Sessions: responses of those expected, minutes, median response time, "
    "dropped frames",
    "pilot_items": "Items: the distribution of each item's ratings (an item everyone answers "
    "the same is named in the data checks)",
    "presentation_quality": "Presentation: frames the clips dropped, per condition (the "
    "session logs' clip_frames_dropped; trials over --max-dropped-frames excluded)",
    "psychometric_fits": "Psychometric fits, P = gamma + (1 - gamma - lambda) F(level): "
    "per participant the posterior with psignifit's default priors (its mode, 95 % profile "
    "intervals), pooled by ML (95 % parametric-bootstrap CIs)",
    "staircase_tracks": "Staircases: every step (level shown, answer, reversal, running estimate)",
    "staircase_thresholds": "Staircases: each participant's threshold per session by the "
    "rule's own estimate (up-down: mean level of the last reversals; QUEST+: posterior mean of "
    "the midpoint); note: a threshold beyond the levels rendered, a bound",
    "identification_summary": "Identification: accuracy and Cohen's kappa",
    "identification_recall": "Identification: recall and precision per label",
    "confusion_matrix": "Identification: confusion counts (portrayed x answered)",
    "identification_by_condition": "Identification: accuracy and Cohen's kappa per condition",
    "identification_condition_model": "Identification: logistic GEE of a right answer on the "
    "condition (exchangeable within participant; Kauermann-Carroll bias-corrected SEs, t tests "
    "with participants "
    "- parameters df; odds ratios against the first condition)",
    "identification_covariates": "Identification with behaviour counts as covariates "
    "(logistic GEE, odds ratios; the counts tested between clips, quasi-binomial GLM of each "
    "clip's answers, df = clips - terms)",
    "sync_window": "Audio-visual timing: each participant's window per condition series "
    "(PSS and width in ms, 95 % profile-likelihood intervals; simultaneity: a Gaussian, width "
    "= full width at half its peak; temporal order: a cumulative Gaussian, width = 25-75 %)",
    "sync_summary": "Audio-visual timing: the participants' mean PSS and width per condition "
    "series (95 % t intervals over <measure>_n participants; a window's PSS or width left "
    "out where its note names it)",
    "sync_tests": "Audio-visual timing: the series compared within participants (RM ANOVA, "
    "Greenhouse-Geisser p, as a = b = all; paired t tests, Holm)",
    "srt": "Speech in noise: each participant's speech reception threshold per condition "
    "series (SNR of 50 % right answers, 95 % profile-likelihood interval; guess rate 1/k), the "
    "benefit against audio alone in dB (Wald interval) and Sumby-Pollack's visual enhancement "
    "at the audio-only SRT",
    "matrix_words": "Word matrix: each word position's share picked right per condition "
    "series (participants' mean, 95 % t interval; the series' SNRs pooled), chance 1 / column "
    "length, and the confusion made most often",
    "srt_summary": "Speech in noise: the participants' mean SRT, benefit and enhancement per "
    "series (95 % t intervals; thresholds not fully determined left out)",
    "srt_tests": "Speech in noise: the series compared within participants (RM ANOVA, "
    "Greenhouse-Geisser p, as a = b = all; paired t tests, Holm)",
    "behaviour_counts": "Behaviour: events per clip, per layer and unit, and motion energy "
    "(from the clips' event logs)",
    "behaviour_covariates": "Behaviour counts as covariates: rating ~ condition + events per "
    "layer (random intercepts per participant and participant x condition, REML; the counts "
    "tested between clips: each clip's mean rating ~ condition + counts, df = clips - terms)",
    "trend_contrast": "Graded design: linear trend contrast of the RM ANOVA (slope per level "
    "unit, own error term)",
    "graded_lmm": "Graded design: mixed model rating ~ level + (1 + level | participant), REML",
}


def _task_headline(tasks: TaskResults | None) -> list[tuple[str, pd.DataFrame]]:
    """The short task tables shown near the top of the report."""
    if tasks is None:
        return []
    out = []
    fits = tasks.tables.get("psychometric_fits")
    if fits is not None:
        pooled = fits[fits["participant"] == "pooled"]
        cols = [
            "task",
            "gamma",
            "n",
            "midpoint",
            "midpoint_ci_low",
            "midpoint_ci_high",
            "slope",
            "lapse",
            "deviance",
            "deviance_df",
        ]
        if pooled["note"].fillna("").astype(str).ne("").any():
            cols.append("note")
        out.append(("Psychometric fits (pooled)", pooled[cols]))
    for name in (
        "staircase_thresholds",
        "identification_summary",
        "identification_by_condition",
        "identification_condition_model",
        "srt_summary",
        "srt_tests",
        "matrix_words",
        "sync_summary",
        "sync_tests",
        "trend_contrast",
        "graded_lmm",
        "presentation_quality",
        "ssq_summary",
        "ssq",
        "ssq_symptoms",
        "conversation_summary",
        "conversation",
        "vr_screen_poses_summary",
        "pilot_sessions",
        "pilot_items",
    ):
        if name in tasks.tables:
            frame = tasks.tables[name]
            if name == "identification_summary":
                frame = frame[frame["participant"] == "pooled"]
            out.append((_TASK_HEADINGS[name].split(":")[0] + ": " + name.replace("_", " "), frame))
    return out


def _task_figures(
    tasks: TaskResults, protocol: Protocol, out: Path, language: str, simulated: bool
) -> list[tuple[str, Path]]:
    blocks: list[tuple[str, Path]] = []
    tag = "  SIMULATED DATA" if simulated else ""
    fits = tasks.tables.get("psychometric_fits")
    for task, counts, curves, gamma in tasks.psychometric:
        undetermined: list[str] = []
        if fits is not None:
            mine = fits[(fits["task"] == task.id) & (fits["participant"] != "pooled")]
            separated = mine["note"].fillna("").astype(str).str.contains("perfect separation")
            undetermined = [str(p) for p in mine.loc[separated, "participant"]]
        fig = figures.psychometric_figure(
            counts,
            curves,
            title=_text(task.question, language),
            xlabel="level of the comparison",
            ylabel="P(correct)" if task.correct == "comparison" else "P(comparison chosen)",
            gamma=gamma,
            caption=f"standard: {task.standard}; grey: participants' fits"
            + ("\ndashed: perfect separation (slope and midpoint not determined)"
               if undetermined else "")
            + tag,
            undetermined=undetermined,
        )  # fmt: skip
        paths = figures.save(fig, out / f"fig_psychometric_{task.id}")
        blocks.append((f"psychometric: {task.id}", paths[0]))
    for task, block_id, track, thresholds in tasks.staircases:
        fig = figures.staircase_figure(
            track,
            thresholds,
            title=f"{_text(task.question, language)} (block {block_id})",
            ylabel="level shown",
            caption=f"rule: {thresholds['rule'].iloc[0]}{tag}",
        )
        paths = figures.save(fig, out / f"fig_staircase_{block_id}")
        blocks.append((f"staircase: {block_id}", paths[0]))
    for task, matrix in tasks.confusion:
        labels = [_text(lb.text, language) for lb in task.labels]
        fig = figures.confusion_figure(
            matrix, labels=labels, title=_text(task.question, language), caption=tag.strip()
        )
        paths = figures.save(fig, out / f"fig_confusion_{task.id}")
        blocks.append((f"confusion: {task.id}", paths[0]))
    conditions = {c.id: c for c in protocol.conditions}
    for task, trials, table in tasks.srt:
        grid = np.linspace(trials["snr_db"].min(), trials["snr_db"].max(), 161)
        counts = (trials.rename(columns={"snr_db": "offset_ms", "units": "n", "hits": "k"})
                  .groupby(["condition", "offset_ms"], sort=False)[["n", "k"]].sum()
                  .reset_index())  # fmt: skip
        order = list(dict.fromkeys(table["condition"]))
        curves = srt.srt_curves(trials, guess=srt.guess_rate(task), snr=grid,
                                order=order).rename(columns={"snr_db": "offset_ms"})  # fmt: skip
        fig = figures.timing_figure(
            counts, curves, labels={}, title=_text(task.question, language),
            ylabel=("P(right word)" if srt.guess_rate(task) > 0
                    else f"P({getattr(task, 'scoring', 'word')[:-1]} right)"),
            xlabel="SNR (dB)",
            caption="lines: fitted to everyone's answers pooled; dotted: 50 % (the SRT)" + tag,
        )  # fmt: skip
        paths = figures.save(fig, out / f"fig_srt_{task.id}")
        blocks.append((f"speech in noise: {task.id}", paths[0]))
    for task, counts, windows in tasks.timing:
        assert task.timing is not None
        grid = np.linspace(counts["offset_ms"].min(), counts["offset_ms"].max(), 161)
        fig = figures.timing_figure(
            counts, timing.window_curves(windows, offsets=grid), labels={},
            title=_text(task.question, language),
            ylabel="P(in sync)" if task.timing.judgment == "simultaneity" else "P(voice first)",
            caption="lines: the function at the participants' median PSS and width" + tag,
        )  # fmt: skip
        paths = figures.save(fig, out / f"fig_timing_{task.id}")
        blocks.append((f"timing: {task.id}", paths[0]))
    for task, matrices in tasks.confusion_by_condition:
        labels = [_text(lb.text, language) for lb in task.labels]
        panels = {_text(conditions[c].label, language): m for c, m in matrices.items()}
        fig = figures.confusion_figure(
            panels, labels=labels, title=_text(task.question, language), caption=tag.strip()
        )
        paths = figures.save(fig, out / f"fig_confusion_{task.id}_by_condition")
        blocks.append((f"confusion by condition: {task.id}", paths[0]))
    return blocks


_CSS = """
body{font-family:'Noto Sans CJK JP','Noto Sans',system-ui,sans-serif;margin:2rem auto;
max-width:1200px;color:#1d2733;padding:0 1rem}
h1{font-size:1.6rem;margin-bottom:.2rem}h2{margin-top:2rem;border-bottom:1px solid #cfd8e3}
.meta{color:#5b6b7c;font-size:.85rem}
.banner{background:#fff3cd;border:1px solid #e0b300;padding:.6rem 1rem;font-weight:600;
margin:1rem 0}
table{border-collapse:collapse;margin:.6rem 0;font-size:.82rem}
th,td{border:1px solid #cfd8e3;padding:.25rem .5rem;text-align:left;vertical-align:top}
th{background:#eef3f8}
.figs{display:flex;flex-wrap:wrap;gap:1rem}figure{margin:0;width:48%}figure img{width:100%}
figcaption{font-size:.8rem;color:#5b6b7c}
"""
