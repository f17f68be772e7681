"""Figures: per item x stimulus set, VAS by condition (like the paper's figures 13-16).

Each figure shows box plots of the participant means per condition, every participant's
means as points joined by a grey line, and brackets for the pairs whose corrected p-value
(the same numbers as the tables) is below .05. No statistics are computed here.
Japanese labels use a CJK font (Noto Sans CJK from Debian's fonts-noto-cjk) when present;
without one, figures fall back to English labels rather than draw empty boxes.
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import pandas as pd
from matplotlib import font_manager
from matplotlib.figure import Figure

__all__ = ["cjk_font", "rating_figure", "stars"]


def cjk_font() -> str | None:
    """Name of an installed font family with Japanese glyphs, or None."""
    names = {f.name for f in font_manager.fontManager.ttflist}
    for name in ("Noto Sans CJK JP", "Noto Sans JP", "IPAexGothic", "IPAGothic", "TakaoGothic"):
        if name in names:
            return name
    return None


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
) -> Figure:
    """One figure.

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
        for _, row in wide.iterrows():
            ax.plot(x, row.to_numpy(), color="0.55", linewidth=0.8, alpha=0.8, zorder=2)
            ax.scatter(x, row.to_numpy(), s=16, color="#1f3b57", zorder=3)
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
        ax.set_xticks(x, labels=list(labels))
        ax.set_ylabel(ylabel)
        ax.set_title("\n".join(textwrap.wrap(title, 34)) if family else title, fontsize=10)
        ax.spines[["top", "right"]].set_visible(False)
        if caption:  # as the x label, so the layout engine makes room for it
            ax.set_xlabel(caption, fontsize=7, color="0.35", labelpad=8)
        return fig


def save(fig: Figure, stem: Path) -> list[Path]:
    """Write ``stem.png`` and ``stem.svg``; returns both paths."""
    paths = [stem.with_suffix(".png"), stem.with_suffix(".svg")]
    for path in paths:
        fig.savefig(path)
    plt.close(fig)
    return paths
