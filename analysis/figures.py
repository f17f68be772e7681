"""Figures: per item x stimulus set, VAS by condition (like the paper's figures 13-16).

Each figure shows box plots of the participant means per condition, every participant's
means as points joined by a grey line, and brackets for the pairs whose corrected p-value
(the same numbers as the tables) is below .05. No statistics are computed here.
Japanese labels use a CJK font (Noto Sans CJK from Debian's fonts-noto-cjk) when present;
without one, figures fall back to English labels rather than draw empty boxes.
"""

from __future__ import annotations

import textwrap
from collections.abc import Collection, Mapping, Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

from facelab.resources import cjk_font

__all__ = [
    "cjk_font",
    "confusion_figure",
    "power_figure",
    "psychometric_figure",
    "rating_figure",
    "staircase_figure",
    "stars",
]


def stars(p: float) -> str:
    return "***" if p < 0.001 else "**" if p < 0.01 else "*" if p < 0.05 else "n.s."


def rating_figure(
    cells: pd.DataFrame,
    *,
    conditions: Sequence[str],
    labels: Sequence[str],
    brackets: pd.DataFrame,
    title: str,
    ylabel: str,
    scale: tuple[float, float] = (0.0, 100.0),
    caption: str = "",
    max_lines: int = 40,
) -> Figure:
    """One figure. With more than ``max_lines`` participants their lines give way to the
    mean and its 95 % CI per condition (1,000 lines show nothing and take seconds to draw).

    Parameters
    ----------
    cells : long table with ``participant, condition, mean`` (participant means).
    conditions, labels : condition ids in x order, and their display labels.
    brackets : ``a, b, p`` rows; those with p < .05 get a bracket with stars and p.
    """
    family = cjk_font()
    rc = {
        "font.family": [family, "DejaVu Sans"] if family else ["DejaVu Sans"],
        "axes.unicode_minus": False,
    }
    with plt.rc_context(rc):
        fig, ax = plt.subplots(figsize=(6.0, 4.8), dpi=150, layout="constrained")
        x = np.arange(len(conditions))
        data = [cells.loc[cells["condition"] == c, "mean"].to_numpy() for c in conditions]
        ax.boxplot(
            data,
            positions=x,
            widths=0.5,
            showfliers=False,
            patch_artist=True,
            boxprops={"facecolor": "#dce6f2", "edgecolor": "#33475b"},
            medianprops={"color": "#1f3b57", "linewidth": 2},
            whiskerprops={"color": "#33475b"},
            capprops={"color": "#33475b"},
        )
        wide = cells.pivot(index="participant", columns="condition", values="mean")
        wide = wide.reindex(columns=list(conditions))
        if len(wide) <= max_lines:  # every participant's means, joined
            for _, row in wide.iterrows():
                ax.plot(x, row.to_numpy(), color="0.55", linewidth=0.8, alpha=0.8, zorder=2)
                ax.scatter(x, row.to_numpy(), s=16, color="#1f3b57", zorder=3)
        else:  # too many to see one by one: the mean with its 95 % CI per condition
            mean = wide.mean().to_numpy()
            half = 1.96 * wide.std(ddof=1).to_numpy() / np.sqrt(wide.notna().sum().to_numpy())
            ax.errorbar(
                x,
                mean,
                yerr=half,
                fmt="o",
                color="#c0504d",
                capsize=4,
                zorder=3,
                label=f"mean and 95 % CI (n = {len(wide)})",
            )
            ax.legend(fontsize=7, loc="lower right", frameon=False)
        low, high = scale
        span = high - low
        top = high
        sig = brackets[brackets["p"] < 0.05]
        for level, r in enumerate(sig.itertuples()):
            i, j = list(conditions).index(r.a), list(conditions).index(r.b)
            y = high + span * (0.06 + 0.09 * level)
            ax.plot([i, i, j, j], [y - span * 0.02, y, y, y - span * 0.02], color="black", lw=1)
            ax.text(
                (i + j) / 2,
                y + span * 0.005,
                f"{stars(r.p)}  p = {r.p:.4f}",
                ha="center",
                va="bottom",
                fontsize=9,
            )
            top = y + span * 0.06
        ax.set_ylim(low - span * 0.03, max(high + span * 0.03, top))
        ax.set_yticks(np.linspace(low, high, 6))
        width = max(8, 48 // max(1, len(labels)))  # characters per line under each box
        ax.set_xticks(x, labels=[textwrap.fill(str(lab), width) for lab in labels])
        ax.set_ylabel(ylabel)
        ax.set_title("\n".join(textwrap.wrap(title, 34)) if family else title, fontsize=10)
        ax.spines[["top", "right"]].set_visible(False)
        if caption:  # as the x label, so the layout engine makes room for it
            ax.set_xlabel(caption, fontsize=7, color="0.35", labelpad=8)
        return fig


def _rc() -> dict:
    family = cjk_font()
    return {
        "font.family": [family, "DejaVu Sans"] if family else ["DejaVu Sans"],
        "axes.unicode_minus": False,
    }


def psychometric_figure(
    counts: pd.DataFrame,
    curves: pd.DataFrame,
    *,
    title: str,
    xlabel: str,
    ylabel: str,
    gamma: float,
    caption: str = "",
    max_lines: int = 40,
    undetermined: Collection[str] = (),
) -> Figure:
    """Pooled proportions at each level (area proportional to n) with the pooled fit, and up
    to ``max_lines`` participants' fitted curves in grey (beyond that, their 10-90 % band);
    the participants in ``undetermined`` (fits the data do not determine, e.g. perfect
    separation) dashed.

    Parameters
    ----------
    counts : pooled ``level, n, k``.
    curves : ``participant, level, p`` fitted curves on a fine grid; ``participant ==
        "pooled"`` is drawn bold.
    """
    with plt.rc_context(_rc()):
        fig, ax = plt.subplots(figsize=(6.0, 4.6), dpi=150, layout="constrained")
        people = curves[curves["participant"] != "pooled"]
        ids = list(dict.fromkeys(people["participant"]))
        if len(ids) <= max_lines:
            for pid in ids:
                one = people[people["participant"] == pid]
                dashed = str(pid) in {str(u) for u in undetermined}
                ax.plot(one["level"], one["p"], color="0.7", lw=0.8, zorder=1,
                        ls="--" if dashed else "-")  # fmt: skip
        elif ids:
            band = people.groupby("level")["p"].quantile([0.1, 0.9]).unstack()
            ax.fill_between(
                band.index,
                band[0.1],
                band[0.9],
                color="0.85",
                zorder=1,
                label=f"10-90 % of {len(ids)} participants",
            )
        pooled = curves[curves["participant"] == "pooled"]
        ax.plot(pooled["level"], pooled["p"], color="#1f3b57", lw=2.2, zorder=3, label="pooled fit")
        prop = counts["k"] / counts["n"]
        size = 400.0 * counts["n"] / counts["n"].max()
        ax.scatter(
            counts["level"],
            prop,
            s=size,
            color="#c0504d",
            alpha=0.75,
            zorder=4,
            edgecolor="white",
            label=f"pooled proportion (area ~ n, largest {int(counts['n'].max())} trials)",
        )
        ax.axhline(gamma, color="0.5", lw=0.8, ls=":", zorder=0)
        ax.set_ylim(-0.03 if gamma == 0 else gamma - 0.08, 1.03)
        ax.set_xlabel(xlabel + (f"\n{caption}" if caption else ""), fontsize=9)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        # below the plot, with a marker of legend size (a data-sized one covered the text)
        legend = fig.legend(fontsize=7, loc="outside lower center", ncol=3, frameon=False)
        for handle in legend.legend_handles:
            if hasattr(handle, "set_sizes"):
                handle.set_sizes([60.0])
        ax.spines[["top", "right"]].set_visible(False)
        return fig


def timing_figure(
    counts: pd.DataFrame,
    curves: pd.DataFrame,
    *,
    labels: Mapping[str, str],
    title: str,
    ylabel: str,
    xlabel: str = "audio offset (ms; negative: the voice first)",
    caption: str = "",
) -> Figure:
    """Audio-visual timing (or words in noise over the SNR): per condition series the pooled
    proportion at each offset (area proportional to n) and the function at the
    participants' median parameters.

    Parameters
    ----------
    counts : ``condition, offset_ms, n, k`` (any participants; pooled here).
    curves : ``condition, offset_ms, p`` on a fine grid.
    labels : series id -> its name in the legend.
    """
    pooled = counts.groupby(["condition", "offset_ms"], sort=False)[["n", "k"]].sum().reset_index()
    colours = plt.get_cmap("tab10").colors
    with plt.rc_context(_rc()):
        fig, ax = plt.subplots(figsize=(6.4, 4.6), dpi=150, layout="constrained")
        for i, series in enumerate(dict.fromkeys([*curves["condition"], *pooled["condition"]])):
            colour = colours[i % len(colours)]
            one = pooled[pooled["condition"] == series]
            line = curves[curves["condition"] == series]
            ax.plot(line["offset_ms"], line["p"], color=colour, lw=2.0,
                    label=labels.get(series, series))  # fmt: skip
            size = 160.0 * one["n"] / pooled["n"].max()
            ax.scatter(one["offset_ms"], one["k"] / one["n"], s=size, color=colour, alpha=0.7,
                       edgecolor="white", zorder=3)  # fmt: skip
        if "offset" in xlabel:
            ax.axvline(0, color="0.5", lw=0.8, ls=":")
        else:
            ax.axhline(0.5, color="0.5", lw=0.8, ls=":")
        ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel(xlabel + (f"\n{caption}" if caption else ""), fontsize=9)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        fig.legend(fontsize=7, loc="outside lower center", ncol=3, frameon=False)
        ax.spines[["top", "right"]].set_visible(False)
        return fig


def staircase_figure(
    track: pd.DataFrame,
    thresholds: pd.DataFrame,
    *,
    title: str,
    ylabel: str,
    caption: str = "",
    max_lines: int = 40,
    max_markers: int = 8,
) -> Figure:
    """Each participant's staircase: the level shown at each step (grey lines; with few
    participants also the answers, filled = correct, open = wrong, and reversals ringed),
    the median level per step (bold), and the median threshold estimate (dashed). Beyond
    ``max_lines`` participants, the 10-90 % band of levels per step instead of lines.

    Parameters
    ----------
    track : ``participant, step, level, correct, reversal`` (one row per step).
    thresholds : ``participant, threshold, estimate`` (one row per participant).
    """
    with plt.rc_context(_rc()):
        fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=150, layout="constrained")
        runs = (track["participant"].astype(str) + "/" + track["session"].astype(str)
                if "session" in track else track["participant"].astype(str))  # fmt: skip
        ids = list(dict.fromkeys(runs))  # a session runs its own staircase
        if len(ids) <= max_lines:
            for k, pid in enumerate(ids):
                one = track[runs == pid]
                ax.step(one["step"], one["level"], where="mid", color="0.7", lw=0.8, zorder=1,
                        label="a participant's levels" if k == 0 else None)  # fmt: skip
                if len(ids) <= max_markers:
                    right = one[one["correct"] == 1]
                    wrong = one[one["correct"] == 0]
                    ax.scatter(right["step"], right["level"], s=14, color="0.35", zorder=2,
                               label="correct" if k == 0 else None)  # fmt: skip
                    ax.scatter(
                        wrong["step"], wrong["level"], s=14, facecolor="white",
                        edgecolor="0.35", zorder=2, label="wrong" if k == 0 else None,
                    )  # fmt: skip
                    rev = one[one["reversal"]]
                    ax.scatter(
                        rev["step"], rev["level"], s=60, facecolor="none",
                        edgecolor="#c0504d", lw=1.0, zorder=3,
                        label="reversal" if k == 0 else None,
                    )  # fmt: skip
        else:
            band = track.groupby("step")["level"].quantile([0.1, 0.9]).unstack()
            ax.fill_between(
                band.index, band[0.1], band[0.9], color="0.85", zorder=1, step="mid",
                label=f"10-90 % of {len(ids)} participants",
            )  # fmt: skip
        median = track.groupby("step")["level"].median()
        ax.step(median.index, median.values, where="mid", color="#1f3b57", lw=2.0, zorder=4,
                label="median level")  # fmt: skip
        kept = (thresholds[thresholds["note"].fillna("").astype(str).eq("")]
                if "note" in thresholds else thresholds)  # a bound is not an estimate
        finite = kept["threshold"].dropna()
        if len(finite):
            estimate = str(thresholds["estimate"].iloc[0])
            ax.axhline(
                float(finite.median()), color="#c0504d", ls="--", lw=1.2, zorder=5,
                label=f"median threshold ({estimate})",
            )  # fmt: skip
        ax.set_xlabel("trial of the staircase" + (f"\n{caption}" if caption else ""), fontsize=9)
        ax.set_ylabel(ylabel)
        ax.set_title(title, fontsize=10)
        # below the figure: inside the axes it lay across the tracks wherever it went
        fig.legend(fontsize=7, loc="outside lower center", ncol=3, frameon=False)
        ax.spines[["top", "right"]].set_visible(False)
        return fig


def confusion_figure(
    matrix: pd.DataFrame | Mapping[str, pd.DataFrame],
    *,
    labels: Sequence[str],
    title: str,
    caption: str = "",
) -> Figure:
    """A heat map of row proportions (each portrayed label's answers sum to 1), with counts;
    given ``{panel title: matrix}`` (e.g. one per condition), one panel each on a shared
    colour scale."""
    panels = dict(matrix) if isinstance(matrix, Mapping) else {"": matrix}
    k, n = len(labels), len(panels)
    with plt.rc_context(_rc()):
        fig, axes = plt.subplots(
            1,
            n,
            figsize=(n * (0.4 + 0.9 * k) + 0.8, 1.0 + 0.8 * k),
            dpi=150,
            layout="constrained",
            squeeze=False,
        )
        for ax, (name, m) in zip(axes[0], panels.items(), strict=True):
            counts = m.to_numpy(dtype=float)
            rows = counts.sum(axis=1, keepdims=True)
            share = np.divide(counts, rows, out=np.zeros_like(counts), where=rows > 0)
            im = ax.imshow(share, cmap="Blues", vmin=0, vmax=1)
            for i in range(k):
                for j in range(k):
                    ax.text(
                        j,
                        i,
                        f"{share[i, j]:.2f}\n({int(counts[i, j])})",
                        ha="center",
                        va="center",
                        fontsize=7,
                        color="white" if share[i, j] > 0.6 else "black",
                    )
            ax.set_xticks(range(k), labels=list(labels), rotation=30, ha="right", fontsize=8)
            ax.set_yticks(range(k), labels=list(labels) if ax is axes[0][0] else [], fontsize=8)
            accuracy = np.trace(counts) / counts.sum() if counts.sum() else float("nan")
            if name:
                ax.set_title(f"{name} (accuracy {accuracy:.2f}, n {int(counts.sum())})", fontsize=9)
        axes[0][0].set_ylabel("portrayed")
        fig.supxlabel("answer" + (f"\n{caption}" if caption else ""), fontsize=8)
        fig.suptitle(title, fontsize=10)
        fig.colorbar(im, ax=list(axes[0]), shrink=0.8, label="share of the row")
        return fig


def power_figure(power: pd.DataFrame, *, target: float, alpha: float, title: str) -> Figure:
    """Power against the number of participants, one line per test (columns of
    :data:`facelab.experiment.simulated_power.POWER_COLUMNS`), with +-1.96 Monte Carlo SE
    bars and the target power as a dashed line."""
    with plt.rc_context(_rc()):
        fig, ax = plt.subplots(figsize=(7.0, 4.2), dpi=150, layout="constrained")
        for (test, kind), part in power.groupby(["test", "kind"], sort=False):
            part = part.sort_values("n")
            power, half = part["power"].to_numpy(), 1.96 * part["mc_se"].to_numpy()
            ax.errorbar(
                part["n"],
                power,
                yerr=[np.minimum(half, power), np.minimum(half, 1 - power)],  # within [0, 1]
                marker="o",
                ms=4,
                capsize=2,
                lw=1.2,
                label=f"{test} ({kind})",
            )
        ax.axhline(target, color="0.3", ls="--", lw=0.8)
        ax.axhline(alpha, color="0.6", ls=":", lw=0.8)
        ax.set_ylim(0, 1.02)
        ax.set_xlabel("participants")
        ax.set_ylabel(f"power (p < {alpha:g})")
        ax.set_title(title, fontsize=10)
        ax.legend(fontsize=7, frameon=False, loc="lower right")
        ax.spines[["top", "right"]].set_visible(False)
        return fig


def save(fig: Figure, stem: Path) -> list[Path]:
    """Write ``stem.png`` and ``stem.svg``; returns both paths."""
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    for path in paths:
        fig.savefig(path)
    plt.close(fig)
    return paths
