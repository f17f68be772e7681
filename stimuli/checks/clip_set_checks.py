"""Stimulus checks for clips made outside a protocol: ``facelab impression render`` (graded
levels of one expression) and ``facelab behaviour render`` (emotion x mode clips). The same
observer and rows as ``facelab check`` (:mod:`.run_checks`), written to
``stimulus_checks.csv`` beside the clips' ``clips.csv``:

* ``face_visible`` per clip (the face tracker's detection and framing);
* ``levels`` per graded group: each step between neighbouring levels changes the face by
  :data:`~facelab.stimuli.checks.clip_checks.FACE_DIFFERENCE` grey levels or more (measured
  in the rendered frames), and the change from the lowest level grows with the level;
* the caller's own rows (an impression level's realised q against the intended one and its
  headroom; the avatar's gaze audit for behaviour clips).

A failure is an error (exit 2) unless its check is accepted by name (``--accept-check``).
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from facelab.stimuli.avatar.mesh import Avatar
from facelab.stimuli.checks.avatar_checks import eye_rows
from facelab.stimuli.checks.clip_checks import face_visible_rows, level_rows
from facelab.stimuli.checks.face_tracker import start_tracking
from facelab.stimuli.checks.rows import CheckRow, accept_checks, at_least, at_most, info
from facelab.stimuli.checks.run_checks import CHECKS_NAME, CheckReport, read_checks, write_checks

__all__ = ["REALISED_SHORTFALL", "behaviour_rows", "check_clip_set", "impression_rows"]

#: a level whose realised q falls short of the intended one by more than this has been eaten
#: by clipping (ARKit channels held at 0 or 1)
REALISED_SHORTFALL = 0.05


def impression_rows(rows: Sequence[Mapping]) -> list[CheckRow]:
    """Per impression clip row (``impression render``'s clips.csv facts): the realised level
    against the intended one (``realised_level``, a warning when clipping eats more than
    :data:`REALISED_SHORTFALL` of it) and the base expression's headroom (``headroom_q``:
    the highest level no channel clips)."""
    out: list[CheckRow] = []
    for r in rows:
        q, real = float(r["q_intended"]), float(r["q_realised"])
        kw = {"clip": r["clip_id"], "condition": "", "check": "levels"}
        eaten = q > 0 and real < q - REALISED_SHORTFALL
        out.append(at_least(
            round(q - REALISED_SHORTFALL, 6) if q > 0 else q, real, measure="realised_level",
            severity="warning", **kw,
            note=(f"clipping eats the level: {r['clipped_channels']} channel(s) held at their "
                  f"limit, q {q:g} shows as {real:.3f}; the expression has room to q = "
                  f"{float(r['headroom_q']):.2f} - lower the level or refit with a smaller "
                  "--step") if eaten else f"{r['clipped_channels']} channel(s) clipped",
        ))  # fmt: skip
        room = "the highest level no ARKit channel clips on this base face"
        out.append(info(float(r["headroom_q"]), measure="headroom_q", note=room, **kw))
    return out


def behaviour_rows(
    rows: Sequence[Mapping], *, avatar: Avatar, clips_dir: Path
) -> list[CheckRow]:
    """For behaviour clips: the avatar's gaze audit (behaviour moves the gaze, so a gaze that
    swings the iris out of the eye is an error) and, per clip, the channels the avatar could
    not show (``dropped_channels``, a warning naming them, from the clip's event log)."""
    out = eye_rows(avatar, severity="error")
    for r in rows:
        path = clips_dir / f"{r['clip_id']}.behaviour.json"
        dropped = json.loads(path.read_text(encoding="utf-8")).get("dropped", {}) \
            if path.is_file() else {}  # fmt: skip
        shown = {k: v for k, v in dropped.items() if "eyeLook" not in v}  # a gaze shown by shapes
        out.append(at_most(0, len(shown), clip=r["clip_id"], condition="", check="avatar_audit",
                           measure="dropped_channels", severity="warning",
                           note="; ".join(f"{k}: {v}" for k, v in shown.items())))  # fmt: skip
    return out


def _kept_from_before(path: Path, clips: set[str]) -> list[CheckRow]:
    """The rows of an earlier ``stimulus_checks.csv`` in the folder about other clips (another
    expression rendered into the same folder keeps its checks, as clips.csv keeps its rows)."""
    if not path.is_file():
        return []
    return [CheckRow.from_dict(r) for r in read_checks(path)
            if r.get("clip") and r["clip"] not in clips]  # fmt: skip


def check_clip_set(
    *,
    clips_dir: Path,
    clips: Sequence[Mapping],
    graded: Mapping[str, Sequence[tuple[float, str]]] | None = None,
    extra: Sequence[CheckRow] = (),
    accept: Sequence[str] = (),
    log: Callable[[str], None] = print,
) -> CheckReport:
    """Track ``clips`` (rows with ``clip_id, path, width, height, duration_s``, paths in
    ``clips_dir``), judge them (see the module docstring; ``graded`` {group: [(level,
    clip id)]}), write ``clips_dir/stimulus_checks.csv`` and return the report (the caller
    raises :meth:`CheckReport.error` on failures)."""
    t0 = time.perf_counter()
    log(f"checking {len(clips)} clips with the face tracker …")
    pending = start_tracking([
        (clips_dir / c["path"], int(c["width"]), int(c["height"]), float(c["duration_s"] or 0))
        for c in clips
    ])  # fmt: skip
    tracked = pending.collect()
    tracking = {c["clip_id"]: tracked[str(clips_dir / c["path"])] for c in clips}
    rows: list[CheckRow] = list(extra)
    for c in clips:
        rows += face_visible_rows(tracking[c["clip_id"]], clip=c["clip_id"], condition="")
    for group, levels in (graded or {}).items():
        rows += level_rows([(q, clip, tracking[clip]) for q, clip in levels],
                           condition_of={}, group=group)  # fmt: skip
    rows = accept_checks(rows, accept)
    rows = _kept_from_before(clips_dir / CHECKS_NAME, {c["clip_id"] for c in clips}) + rows
    tracker = next(iter(tracked.values())).tracker if tracked else ""
    report = CheckReport(rows, tracker=tracker, accepted=tuple(dict.fromkeys(accept)))
    report.path = write_checks(rows, clips_dir / CHECKS_NAME)
    report.seconds = time.perf_counter() - t0
    return report
