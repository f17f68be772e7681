"""Pictures of viseme tracks (like the paper's figures 6 and 7)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
from matplotlib.figure import Figure

from facelab.stimuli.speech.track import VOWELS, VisemeTrack

__all__ = ["vowel_track_figure"]

COLOURS = {"a": "#d62728", "i": "#1f77b4", "u": "#2ca02c", "e": "#ff7f0e", "o": "#9467bd"}


def vowel_track_figure(
    track: VisemeTrack,
    isolated: VisemeTrack | None,
    *,
    title: str,
    source: str = "analyser output",
) -> Figure:
    """The 5 vowel intensities over time; with ``isolated``, a second panel below.
    ``source`` names where the track came from (the first panel's title)."""
    panels = [(source, track)] + ([("vowel isolation", isolated)] if isolated else [])
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


LAYER_COLOURS = {
    "posture": "#8c564b",
    "mannerism": "#1f77b4",
    "gesture": "#d62728",
    "blink": "#7f7f7f",
}


def plan_timeline_figure(
    plan, *, cues=None, phones=(), offset_s: float = 0.0, title: str
) -> Figure:
    """One plan over time: a row per layer with its events (bars labelled by unit, a tick at
    each stroke), and below them the phoneme track of the speech (``phones`` shifted by
    ``offset_s``) with accent peaks and trigger words from ``cues``."""
    from facelab.resources import cjk_font
    from facelab.stimuli.behaviour.library import LAYERS

    font = cjk_font()
    layers = [layer for layer in LAYERS if layer in plan.layers] or list(LAYERS)
    fig, (ax, axp) = plt.subplots(
        2,
        1,
        figsize=(max(9.0, plan.duration_s * 0.45), 1.0 + 0.55 * len(layers) + 1.3),
        dpi=130,
        sharex=True,
        layout="constrained",
        gridspec_kw={"height_ratios": [len(layers), 1.4]},
    )
    for e in plan.events:
        row = len(layers) - 1 - layers.index(e.layer)
        colour = LAYER_COLOURS.get(e.layer, "black")
        ax.broken_barh(
            [(e.start_s, e.end_s - e.start_s)], (row + 0.1, 0.8), color=colour, alpha=0.45
        )
        stroke = e.sync.get("stroke")
        if stroke is not None:
            ax.plot([stroke, stroke], [row + 0.1, row + 0.9], color=colour, lw=1.2)
        if e.end_s - e.start_s > 0.45 or e.layer != "blink":
            ax.text(e.start_s + 0.03, row + 0.5, e.unit, va="center", fontsize=6.5, clip_on=True)
    ax.set_yticks([len(layers) - 1 - i + 0.5 for i in range(len(layers))], layers)
    ax.set_ylim(0, len(layers))
    ax.set_xlim(0, plan.duration_s)
    ax.grid(axis="x", alpha=0.3)
    emo = "; ".join(
        (f"{key['time_s']:g} s: " if len(plan.emotion) > 1 else "")
        + ", ".join(f"{k} {v:g}" for k, v in key.items() if k != "time_s")
        for key in plan.emotion
    )
    ax.set_title(f"{title} - emotion {emo}; seed {plan.seed}", fontsize=10)
    for p in phones:
        if p.phoneme in ("sil", "pau"):
            continue
        a, b = p.start + offset_s, p.end + offset_s
        vowel = p.phoneme.lower() in "aiueo"
        axp.broken_barh([(a, b - a)], (0.1, 0.5), color="#2ca02c" if vowel else "#bbbbbb")
        axp.text((a + b) / 2, 0.35, p.phoneme, ha="center", va="center", fontsize=5.5)
    kw = {"fontfamily": font} if font else {}
    if cues is not None:
        for t in cues.accents:
            axp.plot([t, t], [0.6, 1.0], color="#d62728", lw=1)
        for surface, a, _b in cues.words:
            axp.text(a, 0.72, surface, fontsize=6.5, va="bottom", **kw)
    axp.set_yticks([])
    axp.set_ylim(0, 1.3)
    axp.set_xlabel("clip time (s); red ticks: accent peaks; green: vowels")
    return fig
