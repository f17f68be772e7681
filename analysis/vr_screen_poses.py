"""How participants moved while VR screens waited for their answer (issue 51.3): the head's
and the controllers' poses a VR session records per screen (``_screen_poses.jsonl``:
``viewer_poses`` rows ``[t s, x, y, z m, yaw, pitch, roll deg]``, ``controller_poses`` rows
``[t, hand, x, y, z, yaw, pitch, roll]``, hand 0 left, 1 right, 2 neither), measured.

* ``vr_screen_poses`` - one row per screen shown in VR: participant, session, trial_index,
  screen, item, role; ``seconds`` (first to last pose), ``poses``; the head's ``yaw``,
  ``pitch`` and ``roll`` ranges (deg; yaw unwrapped across +-180) and ``head_travel_m`` (the
  largest distance from where the head was when the screen appeared); ``controllers`` (hands
  tracked) and ``controller_path_m`` (the path length of the most-moved controller).
* ``vr_screen_poses_summary`` - per screen kind: screens, participants, the median seconds,
  the median and largest head yaw range, the median head travel and controller path.

A screen answered before the headset drew a frame has no poses and no row.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import pandas as pd

__all__ = ["screen_pose_summary", "screen_pose_table"]

_KEYS = ("participant", "session", "trial_index", "screen", "item", "role")


def _rows(values: Any, *, width: int) -> np.ndarray:
    """The rows of ``width`` finite numbers among ``values`` (shape (n, width))."""
    out = []
    for row in values if isinstance(values, list) else ():
        if isinstance(row, list) and len(row) == width:
            try:
                numbers = [float(v) for v in row]
            except (TypeError, ValueError):
                continue
            if all(np.isfinite(numbers)):
                out.append(numbers)
    return np.array(out, dtype=float).reshape(-1, width)


def _angle_range(deg: np.ndarray) -> float:
    """The range of angles (deg), unwrapped so that a turn across +-180 is not 360."""
    return float(np.ptp(np.degrees(np.unwrap(np.radians(deg))))) if len(deg) else np.nan


def screen_pose_table(records: Iterable[Mapping[str, Any]]) -> pd.DataFrame:
    """One row per screen record with poses (see the module docstring)."""
    rows = []
    for rec in records:
        head = _rows(rec.get("viewer_poses"), width=7)
        if not len(head):
            continue
        hands = _rows(rec.get("controller_poses"), width=8)
        paths = [
            float(np.linalg.norm(np.diff(hands[hands[:, 1] == hand][:, 2:5], axis=0),
                                 axis=1).sum())
            for hand in np.unique(hands[:, 1])
        ]  # fmt: skip
        rows.append({
            **{k: rec.get(k) for k in _KEYS},
            "seconds": round(float(head[-1, 0] - head[0, 0]), 3),
            "poses": len(head),
            "head_yaw_range_deg": round(_angle_range(head[:, 4]), 2),
            "head_pitch_range_deg": round(_angle_range(head[:, 5]), 2),
            "head_roll_range_deg": round(_angle_range(head[:, 6]), 2),
            "head_travel_m": round(float(np.linalg.norm(head[:, 1:4] - head[0, 1:4],
                                                        axis=1).max()), 4),
            "controllers": len(paths),
            "controller_path_m": round(max(paths), 4) if paths else np.nan,
        })  # fmt: skip
    return pd.DataFrame(rows, columns=[*_KEYS, "seconds", "poses", "head_yaw_range_deg",
                                       "head_pitch_range_deg", "head_roll_range_deg",
                                       "head_travel_m", "controllers", "controller_path_m"])


def screen_pose_summary(table: pd.DataFrame) -> pd.DataFrame:
    """Per screen kind (see the module docstring); empty for an empty table."""
    out = []
    for screen, part in table.groupby("screen", sort=True):
        out.append({
            "screen": screen,
            "screens": len(part),
            "participants": part["participant"].nunique(),
            "median_seconds": round(float(part["seconds"].median()), 3),
            "median_head_yaw_range_deg": round(float(part["head_yaw_range_deg"].median()), 2),
            "max_head_yaw_range_deg": round(float(part["head_yaw_range_deg"].max()), 2),
            "median_head_travel_m": round(float(part["head_travel_m"].median()), 4),
            "median_controller_path_m": round(float(part["controller_path_m"].median()), 4),
        })  # fmt: skip
    return pd.DataFrame(out)
