"""Behaviour statistics from annotated recordings: EMBOS eqs. 2 and 3 (seed 003, §4).

Rules (as ``facelab behaviour fit`` applies them):

* **Input** - a table ``emotion, layer, behaviour, start_s, end_s`` (CSV; an optional ``take``
  column separates recordings for the transition counts), or an ELAN ``.eaf`` file whose tiers
  are named after the layers (``posture``, ``mannerism``, ``gesture``, ``blink``; annotation
  value = behaviour) plus a tier ``emotion`` whose annotations span the acted emotions; each
  behaviour takes the emotion whose span holds its midpoint. Emotions are the seven of
  :data:`~facelab.stimuli.behaviour.library.EMOTIONS`.
* **Amount** of behaviour m in emotion e: the total duration for postures, the number of
  occurrences for mannerisms, gestures and blinks.
* **Universality** s_e(m) = amount_e(m) / Σ_k amount_k(m) (over the emotions k);
  **share** share_e(m) = amount_e(m) / Σ amount_e(m') over the behaviours m' of that layer
  observed in e.
* For emotion e, D = the number of behaviours of the layer observed in e; r = the rank of
  share_e(m) and n = the rank of s_e(m), both among those D, descending (rank 1 = largest),
  ties sharing the smallest rank; E(x) = (D − x + 1)/D;
  **eq. 2**: i_e(m) = α·E(r) + (1 − α)·E(n), α = 0.3. Behaviours not observed in e get 0.
* **Durations**: L_d(e, m) = the mean duration of m's occurrences in e.
* **Eq. 3**: L_w(e, m) = (L_e − ΣL_d)/ΣL_d · L̄_d, with L_e the total posture-annotated time of
  emotion e (the union of its posture intervals) and ΣL_d the total duration of m in e. When
  ΣL_d ≥ L_e the wait is 0 (reported); an emotion without posture annotation is an error.
* **Continuity** ω_c(prev, next) within a layer: transitions between successive occurrences
  (per take and emotion, by start time), add-one smoothed, each row scaled to a maximum of 1.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
from scipy.stats import rankdata

from facelab.errors import BehaviourError
from facelab.stimuli.behaviour.library import EMOTIONS, LAYERS, Library

__all__ = ["ANNOTATION_COLUMNS", "fit_library", "format_report", "read_annotations"]

ANNOTATION_COLUMNS = ("emotion", "layer", "behaviour", "start_s", "end_s")


def read_annotations(path: Path | str) -> pd.DataFrame:
    """A CSV/TSV table or an ELAN ``.eaf`` file -> the checked annotation table."""
    path = Path(path)
    if not path.is_file():
        raise BehaviourError(f"{path}: no such annotation file")
    if path.suffix.lower() == ".eaf":
        table = _read_eaf(path)
    else:
        from facelab.textfiles import read_rows

        rows = read_rows(path, what="annotations", delimiter=None, error=BehaviourError,
                         expected=", ".join(ANNOTATION_COLUMNS))  # fmt: skip
        table = pd.DataFrame(list(rows), columns=rows.header, dtype=str)
        # where each row stands in the file, for the messages
        table["_where"] = [f"line {n}" for n in rows.lines]
    return check_annotations(table, source=str(path))


def _read_eaf(path: Path) -> pd.DataFrame:
    try:
        from pympi.Elan import Eaf
    except ImportError:  # pragma: no cover - pympi-ling is a stimuli dependency
        raise BehaviourError("reading .eaf needs pympi-ling (pip install pympi-ling)") from None
    try:
        eaf = Eaf(str(path))
    except Exception:  # pympi raises bare exceptions (and KeyErrors) on malformed XML
        raise BehaviourError(
            f"{path}: not a readable ELAN file (an .eaf as ELAN saves it: an "
            "ANNOTATION_DOCUMENT with its header, time slots and tiers)"
        ) from None
    tiers = set(eaf.get_tier_names())
    if "emotion" not in tiers:
        raise BehaviourError(f"{path}: needs a tier 'emotion'; tiers: {', '.join(sorted(tiers))}")
    spans = [
        (a / 1000, b / 1000, v.strip())
        for a, b, v, *_ in eaf.get_annotation_data_for_tier("emotion")
    ]
    rows = []
    for layer in LAYERS:
        if layer not in tiers:
            continue
        for a, b, value, *_ in eaf.get_annotation_data_for_tier(layer):
            mid = (a + b) / 2000
            emo = next((e for s, t, e in spans if s <= mid < t), None)
            if emo is None:
                raise BehaviourError(
                    f"{path}: {layer} annotation {value!r} at {a / 1000:.3f} s lies outside every "
                    "'emotion' annotation"
                )
            where = f"tier {layer} at {a / 1000:.3f} s"
            rows.append((emo, layer, value.strip(), a / 1000, b / 1000, where))
    if not rows:
        raise BehaviourError(f"{path}: no tier named {', '.join(LAYERS)} has annotations")
    return pd.DataFrame(rows, columns=[*ANNOTATION_COLUMNS, "_where"])


def check_annotations(table: pd.DataFrame, *, source: str = "annotations") -> pd.DataFrame:
    """Columns, emotions, layers and times checked; errors name where the annotation stands:
    the ``_where`` column when the reader gave one (a CSV's line, an ELAN tier and time), else
    the row (1-based, after the header)."""
    missing = [c for c in ANNOTATION_COLUMNS if c not in table.columns]
    if missing:
        raise BehaviourError(
            f"{source}: missing column(s) {', '.join(missing)}; expected "
            f"{', '.join(ANNOTATION_COLUMNS)}"
        )
    if table.empty:
        raise BehaviourError(f"{source}: no annotations")
    out = table.copy()
    out["emotion"] = out["emotion"].astype(str).str.strip().str.lower()
    out["layer"] = out["layer"].astype(str).str.strip().str.lower()
    out["behaviour"] = out["behaviour"].astype(str).str.strip()
    raw = {col: out[col].tolist() for col in ("start_s", "end_s")}
    for col in ("start_s", "end_s"):
        out[col] = pd.to_numeric(out[col], errors="coerce")
    wheres = (
        out.pop("_where").tolist()
        if "_where" in out.columns
        else [f"row {i}" for i in range(1, len(out) + 1)]
    )
    for n, (i, row) in enumerate(zip(wheres, out.itertuples(index=False), strict=True)):
        if row.emotion not in EMOTIONS:
            raise BehaviourError(
                f"{source}: {i}: emotion {row.emotion!r} is not one of {', '.join(EMOTIONS)}"
            )
        if row.layer not in LAYERS:
            raise BehaviourError(
                f"{source}: {i}: layer {row.layer!r} is not one of {', '.join(LAYERS)}"
            )
        for col in ("start_s", "end_s"):
            if not np.isfinite(getattr(row, col)):
                value = raw[col][n]
                raise BehaviourError(
                    f"{source}: {i}: {col} {value!r} is not a number (expected seconds)"
                )
        if row.end_s <= row.start_s:
            raise BehaviourError(
                f"{source}: {i}: start_s {row.start_s} and end_s {row.end_s} need "
                "end_s > start_s (seconds)"
            )
        if not row.behaviour or row.behaviour == "nan":
            raise BehaviourError(f"{source}: {i}: empty behaviour")
    if "take" not in out.columns:
        out["take"] = "1"
    out["take"] = out["take"].astype(str)
    out["duration_s"] = out["end_s"] - out["start_s"]
    return out


def _union_length(intervals: np.ndarray) -> float:
    total, end = 0.0, -np.inf
    for a, b in sorted(map(tuple, intervals)):
        if b <= end:
            continue
        total += b - max(a, end)
        end = b
    return total


def _E(rank: np.ndarray, d: int) -> np.ndarray:  # noqa: N802 - the seed's name
    return (d - rank + 1) / d


def fit_library(table: pd.DataFrame, *, alpha: float = 0.3) -> tuple[Library, pd.DataFrame]:
    """Eqs. 2-3 on a checked annotation table (:func:`check_annotations`).

    Returns the library (units without motions; merge with
    :meth:`Library.with_motions`) and the long statistics table, one row per observed
    (layer, behaviour, emotion): ``amount, universality, share, D, rank_share,
    rank_universality, intensity, duration_s, total_s, wait_s, wait_note``.
    """
    if not 0 <= alpha <= 1:
        raise BehaviourError(f"alpha {alpha} must lie in [0, 1]")
    posture = table[table["layer"] == "posture"]
    l_e = {
        e: _union_length(posture.loc[posture["emotion"] == e, ["start_s", "end_s"]].to_numpy())
        for e in EMOTIONS
    }
    rows = []
    for layer, lt in table.groupby("layer", sort=False):
        grouped = lt.groupby(["behaviour", "emotion"])
        amount = (
            grouped["duration_s"].sum() if layer == "posture" else grouped["duration_s"].size()
        ).astype(float)
        total_m = amount.groupby(level="behaviour").sum()
        for emo in EMOTIONS:
            if emo not in amount.index.get_level_values("emotion"):
                continue
            am = amount.xs(emo, level="emotion")
            s = am / total_m.loc[am.index]
            share = am / am.sum()
            d = len(am)
            r = rankdata(-share.to_numpy(), method="min")
            n = rankdata(-s.to_numpy(), method="min")
            inten = alpha * _E(r, d) + (1 - alpha) * _E(n, d)
            for j, beh in enumerate(am.index):
                occ = lt[(lt["behaviour"] == beh) & (lt["emotion"] == emo)]["duration_s"]
                total, mean = float(occ.sum()), float(occ.mean())
                if l_e[emo] <= 0:
                    raise BehaviourError(
                        f"emotion {emo!r} has no posture annotation: eq. 3 needs its "
                        "posture-annotated time L_e"
                    )
                note = ""
                wait = (l_e[emo] - total) / total * mean
                if wait < 0:
                    note = f"ΣL_d {total:.2f} s ≥ L_e {l_e[emo]:.2f} s: wait set to 0"
                    wait = 0.0
                rows.append(
                    {
                        "layer": layer,
                        "behaviour": beh,
                        "emotion": emo,
                        "amount": float(am.iloc[j]),
                        "universality": float(s.iloc[j]),
                        "share": float(share.iloc[j]),
                        "D": d,
                        "rank_share": int(r[j]),
                        "rank_universality": int(n[j]),
                        "intensity": float(inten[j]),
                        "duration_s": mean,
                        "total_s": total,
                        "L_e": l_e[emo],
                        "wait_s": float(wait),
                        "wait_note": note,
                    }
                )
    stats = pd.DataFrame(rows)
    units = []
    for (layer, beh), g in stats.groupby(["layer", "behaviour"], sort=False):
        by = g.set_index("emotion")
        units.append(
            {
                "behaviour": beh,
                "layer": layer,
                "intensity": {e: round(float(by["intensity"].get(e, 0.0)), 6) for e in EMOTIONS},
                "duration_s": {e: round(float(v), 6) for e, v in by["duration_s"].items()},
                "wait_s": {e: round(float(v), 6) for e, v in by["wait_s"].items()},
                "observed": {
                    "amount": {e: float(v) for e, v in by["amount"].items()},
                    "universality": {e: round(float(v), 6) for e, v in by["universality"].items()},
                    "share": {e: round(float(v), 6) for e, v in by["share"].items()},
                },
                "source": "facelab behaviour fit (EMBOS eqs. 2-3)",
            }
        )
    library = Library.model_validate(
        {"units": units, "continuity": _continuity(table), "alpha": alpha}
    )
    return library, stats


def _continuity(table: pd.DataFrame) -> dict[str, dict[str, float]]:
    counts: dict[str, dict[str, float]] = {}
    for (_, _, layer), g in table.groupby(["take", "emotion", "layer"], sort=False):
        names = g.sort_values("start_s")["behaviour"].tolist()
        layer_names = sorted(table.loc[table["layer"] == layer, "behaviour"].unique())
        for prev, nxt in zip(["rest", *names[:-1]], names, strict=True):
            row = counts.setdefault(prev, dict.fromkeys(layer_names, 0.0))
            row[nxt] = row.get(nxt, 0.0) + 1
    out = {}
    for prev, row in counts.items():
        smoothed = {k: v + 1 for k, v in row.items()}
        top = max(smoothed.values())
        out[prev] = {k: round(v / top, 6) for k, v in sorted(smoothed.items())}
    return out


def format_report(stats: pd.DataFrame, *, source: str, alpha: float) -> str:
    """A short Markdown report of the fit: one table per layer."""
    lines = [
        f"# Behaviour statistics from {source}",
        "",
        f"EMBOS eq. 2 (α = {alpha}) and eq. 3; rules in `facelab.stimuli.behaviour.fit`.",
        f"{len(stats)} (behaviour, emotion) cells observed.",
        "",
    ]
    for layer in LAYERS:
        g = stats[stats["layer"] == layer]
        if g.empty:
            continue
        unit = "s" if layer == "posture" else "n"
        lines += [
            f"## {layer}",
            "",
            f"| behaviour | emotion | amount ({unit}) | s_e | share | D | r | n | i_e "
            "| L_d s | L_w s |",
            "|---|---|---|---|---|---|---|---|---|---|---|",
        ]
        for row in g.sort_values(["behaviour", "emotion"]).itertuples(index=False):
            lines.append(
                f"| {row.behaviour} | {row.emotion} | {row.amount:g} | {row.universality:.3f} | "
                f"{row.share:.3f} | {row.D} | {row.rank_share} | {row.rank_universality} | "
                f"{row.intensity:.3f} | {row.duration_s:.2f} | {row.wait_s:.2f} |"
            )
        notes = [n for n in g["wait_note"] if n]
        lines += ["", *(f"- {n}" for n in notes), ""] if notes else [""]
    return "\n".join(lines) + "\n"
