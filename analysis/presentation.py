"""Presentation quality as data: the frames each trial's clip dropped (``clip_frames_dropped``
of the session log, lab or online), summarised per condition, and trials over a threshold
left out of the analysis - with what was left out and why stated in the report."""

from __future__ import annotations

import json
import re
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from facelab.errors import AnalysisError
from facelab.formats import LIVE_PLAYBACK_KEYS

__all__ = [
    "FRAME_MEASURES",
    "LIVE_COLUMNS",
    "QUALITY_COLUMNS",
    "exclude_av_offset",
    "exclude_dropped",
    "exclude_trials",
    "frame_measures",
    "live_playback",
    "live_quality",
    "playback_records",
    "playback_replays",
    "presentation_quality",
    "session_modes",
    "session_records",
    "trial_playback",
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
) -> tuple[pd.DataFrame, pd.DataFrame, str]:
    """Responses to trials whose clip dropped more than ``max_dropped`` frames left out:
    ``(kept, excluded, note)``; the note says how many per condition and why, or why
    nothing was left out."""
    dropped = pd.to_numeric(data["clip_frames_dropped"], errors="coerce")
    return _exclude(
        data,
        dropped.fillna(0) > max_dropped,
        f"trials whose clip dropped more than {max_dropped} frames (--max-dropped-frames)",
        measured=dropped.notna(),
    )


def _exclude(
    data: pd.DataFrame, over: pd.Series, why: str, *, measured: pd.Series
) -> tuple[pd.DataFrame, pd.DataFrame, str]:
    """``data`` split by the boolean ``over`` into kept and excluded responses, with the
    report's note: how many responses of how many trials, per condition, and ``why`` - or,
    when nothing was left out, that the rule was applied and why it took nothing (no trial
    carries the measure, or none met it). ``measured``: whether each response's trial carries
    the measure at all (a trial without it is kept, and the note counts them)."""
    kept, excluded = data[~over].reset_index(drop=True), data[over].reset_index(drop=True)
    trials = trials_shown(data)
    unmeasured = len(trials) - len(trials_shown(data[measured]))
    if not measured.any():
        return kept, excluded, (f"{why}: no trial of the sessions carries this measure, so "
                                "nothing was left out")  # fmt: skip
    without = f"; {unmeasured} trial(s) without the measure kept" if unmeasured else ""
    if excluded.empty:
        measured_n = len(trials) - unmeasured
        return kept, excluded, (f"{why}: no trial met it, nothing was left out "
                                f"({measured_n} trials measured{without})")  # fmt: skip
    per = trials_shown(excluded).groupby("condition").size()
    listed = ", ".join(f"{c}: {n}" for c, n in per.items())
    note = f"excluded {len(excluded)} responses of {int(per.sum())} {why}, per condition {listed}"
    return kept, excluded, note + without


#: the live 3D / VR views' per-clip measures (``_playback.jsonl``; facelab serve with
#: ``presentation.display: live3d | webxr``) joined to each trial by :func:`with_live_playback`
LIVE_COLUMNS = LIVE_PLAYBACK_KEYS


def playback_records(data: pd.DataFrame) -> list[dict[str, Any]]:
    """Every ``_playback.jsonl`` record beside the session logs ``data`` was read from (its
    ``source`` column), each with its session's ``participant`` and ``session``; a line cut
    off mid-write is passed over (the trial's earlier record stands)."""
    return session_records(data, suffix="_playback.jsonl")


def session_records(data: pd.DataFrame, *, suffix: str) -> list[dict[str, Any]]:
    """Every record of the JSON-lines file ``<session stem><suffix>`` beside the session logs
    ``data`` was read from, each with its session's ``participant`` and ``session``; a line
    cut off mid-write is passed over."""
    out = []
    sessions = data[["source", "participant", "session"]].drop_duplicates("source")
    for source, participant, session in sessions.itertuples(index=False):
        tsv = Path(source)
        path = tsv.with_name(tsv.name.replace("_beh.tsv", suffix))
        if not path.is_file():
            continue
        for line in path.read_text(encoding="utf-8").split("\n"):  # (not U+2028 in a string)
            if not line.strip():
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            out.append(record | {"participant": participant, "session": int(session)})
    return out


#: measures derived from a record's frames (video and live alike), see :func:`frame_measures`
FRAME_MEASURES = ("frame_age_max_ms", "frames_frozen", "frames_never_shown_share")


def frame_measures(record: Mapping[str, Any]) -> dict[str, float | None]:
    """What a clip's displayed frames say (``flip_times`` s, ``frames_shown`` the clip frame
    on each, ``frames_expected``): ``frame_age_max_ms`` the longest time one clip frame
    stayed on screen (from its first flip to the flip that replaced it) - a frozen picture
    shows here, whatever the A/V offset says; ``frames_frozen`` the flip gaps longer than two
    clip frame periods; ``frames_never_shown_share`` the clip's frames never on screen. None
    where the record has no frames."""
    flips = [float(t) for t in record.get("flip_times") or []]
    shown = list(record.get("frames_shown") or [])
    n = int(record.get("frames_expected") or 0)
    if len(flips) < 2 or len(shown) != len(flips) or n <= 0:
        return dict.fromkeys(FRAME_MEASURES)
    duration = float(record.get("media_time_end") or 0) or None
    period = (duration / n) if duration else float(np.median(np.diff(flips)))
    age, start = 0.0, flips[0]
    for t, prev, cur in zip(flips[1:], shown[:-1], shown[1:], strict=True):
        if cur != prev:
            age, start = max(age, t - start), t
    gaps = np.diff(flips)
    return {
        "frame_age_max_ms": round(1000 * age, 2),
        "frames_frozen": int(np.sum(gaps > 2 * period)),
        "frames_never_shown_share": round(1 - len(set(shown)) / n, 4),
    }


def _last_showings(
    records: list[dict[str, Any]], *, fields: Callable[[dict[str, Any]], dict[str, Any]],
    columns: Sequence[str],
) -> pd.DataFrame:  # fmt: skip
    """One row per (participant, session, trial_index) of ``records``: ``fields(record)``
    and its :func:`frame_measures`, the trial's last showing kept (a replay after a resume
    is what the answer followed); ``columns`` when there is none."""
    rows = [{k: r.get(k) for k in _TRIAL} | fields(r) | frame_measures(r)
            for r in records if r.get("trial_index")]  # fmt: skip
    if not rows:
        return pd.DataFrame(columns=list(columns))
    frame = pd.DataFrame(rows).astype({"trial_index": int})
    return frame.drop_duplicates(_TRIAL, keep="last").reset_index(drop=True)


def trial_playback(records: list[dict[str, Any]]) -> pd.DataFrame:
    """One row per (participant, session, trial_index) shown: every number its last showing
    recorded (``dropped``, ``av_offset_ms``, ``head_yaw_range_deg``, …) and its
    :func:`frame_measures` - what ``--exclude-trials`` reads."""

    def numbers(r: dict[str, Any]) -> dict[str, Any]:
        return {k: v for k, v in r.items() if k not in _TRIAL and isinstance(v, int | float)
                and not isinstance(v, bool)}  # fmt: skip

    return _last_showings(records, fields=numbers, columns=[*_TRIAL, *FRAME_MEASURES])


_RULE = re.compile(
    r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(>=|<=|==|!=|>|<)\s*"
    r"([-+]?\d+(?:\.\d*)?(?:[eE][-+]?\d+)?)\s*$"
)
_OPS = {">": np.greater, ">=": np.greater_equal, "<": np.less, "<=": np.less_equal,
        "==": np.equal, "!=": np.not_equal}  # fmt: skip


def exclude_trials(
    data: pd.DataFrame, records: list[dict[str, Any]], *, rules: Sequence[str]
) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """Responses to trials whose playback record meets any rule left out (``rules``: e.g.
    ``"head_yaw_range_deg > 30"``, a measure of :func:`trial_playback`, a comparison and a
    number): ``(kept, excluded, notes)``, a note per rule (how many it left out per
    condition, or why it left nothing out). A trial without the measure (not recorded) is
    kept. An unknown measure or a rule that does not parse is an :class:`AnalysisError`
    naming what is known."""
    table = trial_playback(records)
    known = sorted(set(table.columns) - set(_TRIAL))
    excluded_all, notes = data.iloc[:0], []
    for rule in rules:
        m = _RULE.match(rule)
        if m is None:
            raise AnalysisError(f"--exclude-trials {rule!r}: expected MEASURE OP NUMBER, e.g. "
                                "\"head_yaw_range_deg > 30\" (OP: > >= < <= == !=)")  # fmt: skip
        measure, op, value = m.group(1), m.group(2), float(m.group(3))
        if measure not in known:
            raise AnalysisError(f"--exclude-trials {rule!r}: no playback measure {measure!r}; "
                                f"the records have: {', '.join(known) or 'none'}")  # fmt: skip
        merged = data[list(_TRIAL)].merge(table[[*_TRIAL, measure]], on=list(_TRIAL),
                                          how="left")  # fmt: skip
        values = pd.to_numeric(merged[measure], errors="coerce").to_numpy(float)
        over = pd.Series(_OPS[op](values, value) & ~np.isnan(values), index=data.index)
        has = pd.Series(~np.isnan(values), index=data.index)
        data, excluded, note = _exclude(data, over, f"trials where {measure} {op} {value:g} "
                                        "(--exclude-trials)", measured=has)  # fmt: skip
        notes.append(note)
        if not excluded.empty:
            excluded_all = pd.concat([excluded_all, excluded], ignore_index=True)
    return data, excluded_all, notes


def live_playback(records: list[dict[str, Any]]) -> pd.DataFrame:
    """One row per (participant, session, trial_index) shown live: the measures of the
    trial's last showing (a replay after a resume is what the answer followed), from the
    :func:`playback_records`. Empty when no clip was drawn live (video studies, lab
    sessions)."""
    live = [r for r in records if r.get("display") in ("live3d", "webxr")]
    return _last_showings(live, fields=lambda r: {k: r.get(k) for k in LIVE_COLUMNS},
                          columns=[*_TRIAL, *LIVE_COLUMNS, *FRAME_MEASURES])  # fmt: skip


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
                "session": info.get("session", 1),  # a whole number (checked by the loader)
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
    for col in (*LIVE_COLUMNS, *FRAME_MEASURES):
        out[col] = merged[col].to_numpy()
    return out


def live_quality(data: pd.DataFrame) -> pd.DataFrame:
    """Per stimulus set and condition, for trials shown live: trials, the display that ran,
    the median and largest |A/V offset| (ms), frames late, in VR the median head yaw and
    pitch ranges (deg) and viewing distance (m), and the largest frame age (ms), the freezes
    and the median share of frames never shown (:func:`frame_measures`)."""
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
                # a frozen picture the A/V offset cannot see (frame_measures)
                "max_frame_age_ms": _largest(part, "frame_age_max_ms"),
                "frames_frozen": int(_numbers(part, "frames_frozen").fillna(0).sum()),
                "median_frames_never_shown_share": _median(part, "frames_never_shown_share"),
            }
        )
    return pd.DataFrame(rows)


def _numbers(part: pd.DataFrame, column: str) -> pd.Series:
    if column not in part.columns:
        return pd.Series(np.nan, index=part.index)
    return pd.to_numeric(part[column], errors="coerce")


def _largest(part: pd.DataFrame, column: str) -> float:
    return round(float(_numbers(part, column).max()), 2)


def _median(part: pd.DataFrame, column: str) -> float:
    return round(float(_numbers(part, column).median()), 4)


def exclude_av_offset(
    data: pd.DataFrame, *, max_ms: float
) -> tuple[pd.DataFrame, pd.DataFrame, str]:
    """Responses to live trials whose |A/V offset| exceeded ``max_ms`` left out:
    ``(kept, excluded, note)`` as :func:`exclude_dropped`."""
    offset = pd.Series(np.nan, index=data.index)
    if "av_offset_ms" in data.columns:
        offset = pd.to_numeric(data["av_offset_ms"], errors="coerce").abs()
    return _exclude(
        data,
        offset > max_ms,
        f"live trials whose picture and sound were more than {max_ms:g} ms apart "
        "(--max-av-offset-ms; measured only where clips were drawn live, display live3d or "
        "webxr)",
        measured=offset.notna(),
    )
