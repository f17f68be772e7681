"""Presentation quality as data: the frames each trial's clip dropped (``clip_frames_dropped``
of the session log, lab or online), summarised per condition, and trials over a threshold
left out of the analysis - with what was left out and why stated in the report."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pandas as pd

from facelab.formats import LIVE_PLAYBACK_KEYS

__all__ = [
    "LIVE_COLUMNS",
    "QUALITY_COLUMNS",
    "exclude_av_offset",
    "exclude_dropped",
    "live_playback",
    "live_quality",
    "playback_records",
    "playback_replays",
    "presentation_quality",
    "session_modes",
    "trials_shown",
    "with_live_playback",
]

QUALITY_COLUMNS = (
    "stimulus_set",
    "condition",
    "trials",
    "trials_with_drops",
    "frames_dropped",
    "max_dropped",
    "excluded_trials",
    "replays",
)
_TRIAL = ["participant", "session", "trial_index"]


def trials_shown(data: pd.DataFrame) -> pd.DataFrame:
    """One row per shown trial (its responses share the clip): the keys, the stimulus set,
    the condition and the frames dropped (NaN when the log has no playback record)."""
    if data.empty:
        return pd.DataFrame(columns=[*_TRIAL, "stimulus_set", "condition", "dropped"])
    trials = data.drop_duplicates(_TRIAL)[[*_TRIAL, "stimulus_set", "condition"]].copy()
    trials["dropped"] = pd.to_numeric(
        data.drop_duplicates(_TRIAL)["clip_frames_dropped"], errors="coerce"
    ).to_numpy()
    return trials


def presentation_quality(
    data: pd.DataFrame,
    *,
    excluded: pd.DataFrame | None = None,
    replays: pd.DataFrame | None = None,
) -> pd.DataFrame:
    """Per stimulus set and condition: trials shown, trials whose clip dropped frames, frames
    dropped in all and at most in one trial, trials excluded (``excluded``: responses left out
    by :func:`exclude_dropped`) and clips shown again after a resume (``replays``, from
    :func:`playback_replays`)."""
    both = data if excluded is None or excluded.empty else pd.concat([data, excluded])
    trials = trials_shown(both)
    gone = trials_shown(excluded) if excluded is not None else None
    out_keys = set() if gone is None else set(map(tuple, gone[_TRIAL].to_numpy()))
    trials["excluded"] = [tuple(k) in out_keys for k in trials[_TRIAL].to_numpy()]
    again = {} if replays is None else {
        (r.participant, int(r.session), int(r.trial_index)): int(r.replays)
        for r in replays.itertuples()
    }  # fmt: skip
    trials["replays"] = [
        again.get((pid, int(ses), int(t)), 0) for pid, ses, t in trials[_TRIAL].to_numpy()
    ]
    rows = []
    for (sset, cond), part in trials.groupby(["stimulus_set", "condition"], sort=True):
        dropped = part["dropped"].fillna(0)
        rows.append(
            {
                "stimulus_set": sset,
                "condition": cond,
                "trials": len(part),
                "trials_with_drops": int((dropped > 0).sum()),
                "frames_dropped": int(dropped.sum()),
                "max_dropped": int(dropped.max()) if len(part) else 0,
                "excluded_trials": int(part["excluded"].sum()),
                "replays": int(part["replays"].sum()),
            }
        )
    return pd.DataFrame(rows, columns=list(QUALITY_COLUMNS))


def exclude_dropped(
    data: pd.DataFrame, *, max_dropped: int
) -> tuple[pd.DataFrame, pd.DataFrame, str | None]:
    """Responses to trials whose clip dropped more than ``max_dropped`` frames left out:
    ``(kept, excluded, note)``; the note (None when nothing was left out) says how many per
    condition and why."""
    dropped = pd.to_numeric(data["clip_frames_dropped"], errors="coerce").fillna(0)
    return _exclude(
        data,
        dropped > max_dropped,
        f"trials whose clip dropped more than {max_dropped} frames (--max-dropped-frames)",
    )


def _exclude(
    data: pd.DataFrame, over: pd.Series, why: str
) -> tuple[pd.DataFrame, pd.DataFrame, str | None]:
    """``data`` split by the boolean ``over`` into kept and excluded responses, with the
    report's note (how many responses of how many trials, per condition, and ``why``)."""
    kept, excluded = data[~over].reset_index(drop=True), data[over].reset_index(drop=True)
    if excluded.empty:
        return kept, excluded, None
    per = trials_shown(excluded).groupby("condition").size()
    listed = ", ".join(f"{c}: {n}" for c, n in per.items())
    note = f"excluded {len(excluded)} responses of {int(per.sum())} {why}, per condition {listed}"
    return kept, excluded, note


#: the live 3D / VR views' per-clip measures (``_playback.jsonl``; facelab serve with
#: ``presentation.display: live3d | webxr``) joined to each trial by :func:`with_live_playback`
LIVE_COLUMNS = LIVE_PLAYBACK_KEYS


def playback_records(data: pd.DataFrame) -> list[dict[str, Any]]:
    """Every ``_playback.jsonl`` record beside the session logs ``data`` was read from (its
    ``source`` column), each with its session's ``participant`` and ``session``; a line cut
    off mid-write is passed over (the trial's earlier record stands)."""
    out = []
    sessions = data[["source", "participant", "session"]].drop_duplicates("source")
    for source, participant, session in sessions.itertuples(index=False):
        tsv = Path(source)
        path = tsv.with_name(tsv.name.replace("_beh.tsv", "_playback.jsonl"))
        if not path.is_file():
            continue
        for line in path.read_text(encoding="utf-8").splitlines():
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            out.append(record | {"participant": participant, "session": int(session)})
    return out


def live_playback(records: list[dict[str, Any]]) -> pd.DataFrame:
    """One row per (participant, session, trial_index) shown live: the measures of the
    trial's last showing (a replay after a resume is what the answer followed), from the
    :func:`playback_records`. Empty when no clip was drawn live (video studies, lab
    sessions)."""
    rows = [
        {k: r.get(k) for k in (*_TRIAL, *LIVE_COLUMNS)}
        for r in records
        if r.get("display") in ("live3d", "webxr") and r.get("trial_index")
    ]
    if not rows:
        return pd.DataFrame(columns=[*_TRIAL, *LIVE_COLUMNS])
    frame = pd.DataFrame(rows).astype({"trial_index": int})
    return frame.drop_duplicates(_TRIAL, keep="last").reset_index(drop=True)


def playback_replays(records: list[dict[str, Any]]) -> pd.DataFrame:
    """Per (participant, session, trial_index): how many times its clip was shown again after
    a resume or reload (``replay: true`` :func:`playback_records`), lab and online alike."""
    rows = [{k: r[k] for k in _TRIAL} for r in records if r.get("replay") and r.get("trial_index")]
    if not rows:
        return pd.DataFrame(columns=[*_TRIAL, "replays"])
    frame = pd.DataFrame(rows).astype({"trial_index": int})
    return frame.groupby(_TRIAL).size().rename("replays").reset_index()


def session_modes(data: pd.DataFrame) -> pd.DataFrame:
    """Per (participant, session) of the logs ``data`` was read from: where it ran (``mode``
    of the session JSON: ``lab``, ``online``; simulated sessions say so) and, online, the
    display that ran."""
    rows = []
    for source in data["source"].dropna().unique():
        tsv = Path(source)
        path = tsv.with_name(tsv.name.replace("_beh.tsv", "_session.json"))
        try:
            info = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            continue
        display = info.get("display") if isinstance(info.get("display"), dict) else None
        rows.append(
            {
                "participant": info.get("participant"),
                "session": int(info.get("session", 1)),
                "mode": str(info.get("mode") or "lab"),
                "simulated": bool(info.get("simulated")),
                "display": (display or {}).get("ran", "video"),
            }
        )
    return pd.DataFrame(rows, columns=["participant", "session", "mode", "simulated", "display"])


def with_live_playback(data: pd.DataFrame, live: pd.DataFrame) -> pd.DataFrame:
    """``data`` with :data:`LIVE_COLUMNS` per trial (NaN for trials not shown live)."""
    if live.empty:
        return data
    keys = data[_TRIAL].astype({"session": int, "trial_index": int})
    merged = keys.merge(live, on=_TRIAL, how="left")
    out = data.copy()
    for col in LIVE_COLUMNS:
        out[col] = merged[col].to_numpy()
    return out


def live_quality(data: pd.DataFrame) -> pd.DataFrame:
    """Per stimulus set and condition, for trials shown live: trials, the display that ran,
    the median and largest |A/V offset| (ms), frames late, and in VR the median head yaw and
    pitch ranges (deg) and viewing distance (m)."""
    if "av_offset_ms" not in data.columns:
        return pd.DataFrame()
    trials = data.drop_duplicates(_TRIAL)
    trials = trials[trials["display"].notna()]
    rows = []
    for (sset, cond), part in trials.groupby(["stimulus_set", "condition"], sort=True):
        off = pd.to_numeric(part["av_offset_ms"], errors="coerce").abs()
        num = {c: pd.to_numeric(part[c], errors="coerce") for c in LIVE_COLUMNS[2:]}
        rows.append(
            {
                "stimulus_set": sset,
                "condition": cond,
                "trials": len(part),
                "display": ",".join(sorted(part["display"].astype(str).unique())),
                "median_abs_av_offset_ms": round(float(off.median()), 2),
                "max_abs_av_offset_ms": round(float(off.max()), 2),
                "frames_late": int(num["frames_late"].fillna(0).sum()),
                "median_head_yaw_range_deg": round(float(num["head_yaw_range_deg"].median()), 2),
                "median_head_pitch_range_deg": round(
                    float(num["head_pitch_range_deg"].median()), 2
                ),
                "median_avatar_distance_m": round(float(num["avatar_distance_m"].median()), 3),
            }
        )
    return pd.DataFrame(rows)


def exclude_av_offset(
    data: pd.DataFrame, *, max_ms: float
) -> tuple[pd.DataFrame, pd.DataFrame, str | None]:
    """Responses to live trials whose |A/V offset| exceeded ``max_ms`` left out:
    ``(kept, excluded, note)`` as :func:`exclude_dropped`."""
    if "av_offset_ms" not in data.columns:
        return data, data.iloc[:0], None
    over = pd.to_numeric(data["av_offset_ms"], errors="coerce").abs() > max_ms
    return _exclude(
        data,
        over,
        f"live trials whose picture and sound were more than {max_ms:g} ms apart "
        "(--max-av-offset-ms)",
    )
