"""Pictures of viseme tracks (like the paper's figures 6 and 7)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.figure import Figure

from facelab.stimuli.visemes import VOWELS, VisemeTrack

__all__ = ["vowel_track_figure"]

COLOURS = {"a": "#d62728", "i": "#1f77b4", "u": "#2ca02c", "e": "#ff7f0e", "o": "#9467bd"}


def vowel_track_figure(track: VisemeTrack, isolated: VisemeTrack | None, *, title: str) -> Figure:
    """The 5 vowel intensities over time; with ``isolated``, a second panel below."""
    panels = [("analyser output", track)] + ([("vowel isolation", isolated)] if isolated else [])
    fig, axes = plt.subplots(
        len(panels),
        1,
        figsize=(9, 2.6 * len(panels)),
        dpi=130,
        sharex=True,
        layout="constrained",
        squeeze=False,
    )
    for ax, (label, tr) in zip(axes[:, 0], panels, strict=True):
        vowels = tr.vowels()
        for j, v in enumerate(VOWELS):
            ax.plot(tr.times, vowels[:, j], color=COLOURS[v], lw=1.4, label=v)
        ax.set_ylim(-0.02, 1.02)
        ax.set_ylabel("intensity")
        ax.set_title(f"{title}: {label}", fontsize=10)
        ax.legend(loc="upper right", ncols=5, fontsize=8, frameon=False)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time (s)")
    return fig
