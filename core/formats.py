"""File formats that cross layers, each with its one reader (and writer where shared):

* the clip manifest ``clips.csv`` (DESIGN.md: :data:`CLIP_COLUMNS`) written by the stimulus
  layer, read by sessions, the online server and the analysis (:func:`read_manifest`,
  :func:`write_manifest`);
* the behaviour event log ``<clip_id>.behaviour.json`` beside a clip (:func:`read_behaviour_log`);
* a clip's animation track ``<clip_id>.track.bin`` (:func:`encode_track`, :func:`read_track`):
  the exact per-frame values a clip was drawn with, for the offline renderer and the browser;
* the impression model file's header (:data:`IMPRESSION_FORMAT`,
  :func:`impression_header_problems`), checked by the protocol loader without reading the model.

``write_manifest`` writes atomically and, for the tools that render part of a set at a time
(``facelab impression render`` one expression, ``facelab behaviour render`` some emotions),
keeps the rows of clips rendered earlier into the same folder. A kept row must name a clip
that is not rendered now, whose file is still in the folder, and come from a manifest with the
same columns; anything else is dropped and named, so the manifest never lists a file that is
gone and never forgets one that is there.
"""

from __future__ import annotations

import csv
import json
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facelab.durable import replace_file
from facelab.errors import FormatError, StageError

__all__ = [
    "BEHAVIOUR_LOG_SUFFIX",
    "CHECKS_COLUMN",
    "CLIP_COLUMNS",
    "FACE_TRACKING_COLUMNS",
    "FACE_TRACKING_NAME",
    "IMPRESSION_FORMAT",
    "LIVE_PLAYBACK_KEYS",
    "MANIFEST_NAME",
    "POSE_CHANNELS",
    "STIMULUS_CHECKS_NAME",
    "STIMULUS_CHECK_COLUMNS",
    "TRACK_COLUMNS",
    "TRACK_FORMAT",
    "Track",
    "behaviour_log_path",
    "checks_failed",
    "decode_track",
    "encode_track",
    "impression_header_problems",
    "read_behaviour_log",
    "read_face_tracking_rows",
    "read_manifest",
    "read_stimulus_checks",
    "read_track",
    "track_path",
    "write_face_tracking",
    "write_manifest",
]

#: the clip manifest's file name and columns (DESIGN.md); a protocol's clips have them all
MANIFEST_NAME = "clips.csv"
CLIP_COLUMNS = (
    "clip_id",
    "stimulus_set",
    "stimulus",
    "condition",
    "path",
    "duration_s",
    "fps",
    "width",
    "height",
    "sha256",
    "spec_sha256",
)
#: columns ``facelab render`` adds after :data:`CLIP_COLUMNS`: each clip's animation track file
#: and its SHA-256 (not required of manifests written before tracks existed)
TRACK_COLUMNS = ("track_file", "track_sha256")
#: the column ``facelab check`` adds to ``clips.csv``: each clip's check outcome, ``passed``,
#: or ``failed: NAMES`` / ``accepted: NAMES`` for the checks that failed on it
CHECKS_COLUMN = "stimulus_checks"
#: the suffix of a clip's animation track, beside the clip
TRACK_SUFFIX = ".track.bin"
#: the animation track's magic bytes and format id (see :func:`encode_track`)
TRACK_MAGIC = b"FLTRACK1"
TRACK_FORMAT = "facelab-track-1"
#: the head-pose channels of a track, in this order after the blendshape channels
POSE_CHANNELS = ("head_yaw", "head_pitch", "head_roll", "eye_yaw", "eye_pitch", "neck_share")
#: the measures a live 3D / VR view adds to a clip's ``_playback.jsonl`` record (facelab serve
#: with ``presentation.display: live3d | webxr``; absent from video and lab records)
LIVE_PLAYBACK_KEYS = (
    "display",
    "av_offset_ms",
    "frames_late",
    "head_yaw_range_deg",
    "head_pitch_range_deg",
    "avatar_distance_m",
)
#: the suffix of a clip's behaviour event log, beside the clip
BEHAVIOUR_LOG_SUFFIX = ".behaviour.json"
#: the format id in an impression model file (``facelab impression fit``)
IMPRESSION_FORMAT = "facelab-impression-1"


#: the stimulus checks beside clips.csv (DESIGN.md's columns, then severity and accepted):
#: written by ``facelab check`` / ``render``, read by the analysis report
STIMULUS_CHECKS_NAME = "stimulus_checks.csv"
STIMULUS_CHECK_COLUMNS = (
    "clip",
    "condition",
    "check",
    "measure",
    "value",
    "threshold",
    "passed",
    "note",
    "severity",
    "accepted",
)


def _read_csv_rows(
    path: Path, *, what: str, need: Sequence[str], remedy: str
) -> list[dict[str, str]]:
    """The rows of the CSV file ``path`` (strings), each with at least the columns ``need``;
    :class:`FormatError` naming the file when it is unreadable or lacks one (then ``remedy``)."""
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = list(reader.fieldnames or [])
            rows = list(reader)
    except (OSError, UnicodeDecodeError, csv.Error):
        raise FormatError(f"{path}: not a readable CSV {what}") from None
    lacking = [c for c in need if c not in header]
    if lacking:
        raise FormatError(f"{path}: no column {', '.join(lacking)}; {remedy}")
    return rows


#: the face tracker's per-frame measures of every checked clip, written by the stimulus checks
#: beside stimulus_checks.csv and read by the analysis' objective comparison: one row per
#: clip and frame; aperture and width over the face height, NaN where no face was found
FACE_TRACKING_NAME = "face_tracking.csv"
FACE_TRACKING_COLUMNS = ("clip", "frame", "time_s", "detection", "aperture", "width",
                         "face_height")  # fmt: skip


def write_face_tracking(
    clips_dir: Path, frames: Sequence[dict[str, Any]], *, keep_other_clips: bool = True
) -> Path:
    """``clips_dir/face_tracking.csv`` (:data:`FACE_TRACKING_COLUMNS`) from ``frames`` (one
    mapping per clip and frame), atomically; rows of clips not in ``frames`` are kept."""
    path = Path(clips_dir) / FACE_TRACKING_NAME
    now = {str(f["clip"]) for f in frames}
    kept = []
    if keep_other_clips and path.is_file():
        kept = [r for r in read_face_tracking_rows(clips_dir) if r["clip"] not in now]
    lines = [",".join(FACE_TRACKING_COLUMNS)]
    for row in [*kept, *frames]:
        lines.append(",".join(_cell(row[c]) for c in FACE_TRACKING_COLUMNS))
    replace_file(path, "\n".join(lines) + "\n")
    return path


def _cell(value: Any) -> str:
    if isinstance(value, float):
        return "" if not np.isfinite(value) else f"{value:.6g}"
    return str(value)


def read_face_tracking_rows(clips_dir: Path) -> list[dict[str, str]]:
    """The rows of ``clips_dir/face_tracking.csv`` (strings; empty list when there is none).
    Raises :class:`FormatError` naming the file when it is unreadable or lacks a column."""
    path = Path(clips_dir) / FACE_TRACKING_NAME
    if not path.is_file():
        return []
    return _read_csv_rows(path, what="of face tracking", need=FACE_TRACKING_COLUMNS,
                          remedy="run `facelab check` on the clips again")  # fmt: skip


def read_stimulus_checks(clips_dir: Path) -> list[dict[str, str]] | None:
    """The rows of ``clips_dir/stimulus_checks.csv`` (strings), or None when the clips were
    never checked. Raises :class:`FormatError` naming the file when it is unreadable or lacks
    a column."""
    path = Path(clips_dir) / STIMULUS_CHECKS_NAME
    if not path.is_file():
        return None
    return _read_csv_rows(
        path, what="of stimulus checks", need=STIMULUS_CHECK_COLUMNS,
        remedy="run `facelab check` on the clips again",
    )  # fmt: skip


def read_manifest(clips_dir: Path, *, need: Sequence[str] = ()) -> list[dict[str, str]]:
    """The rows of ``clips_dir/clips.csv`` (strings), each with at least the columns
    ``need``. Raises :class:`FormatError` naming the file when it is missing, unreadable or
    lacks a needed column."""
    path = Path(clips_dir) / MANIFEST_NAME
    if not path.is_file():
        raise FormatError(f"no clip manifest at {path}: render the clips first")
    return _read_csv_rows(
        path, what="clip manifest", need=need,
        remedy="written by an older facelab? render the clips again",
    )  # fmt: skip


@dataclass(frozen=True)
class Track:
    """A decoded animation track: its JSON ``header`` and ``values`` (n_frames, n_channels)
    float32, column j being channel ``header["channels"][j]["name"]``."""

    header: dict[str, Any]
    values: np.ndarray

    @property
    def names(self) -> list[str]:
        return [c["name"] for c in self.header["channels"]]

    def channel(self, name: str) -> np.ndarray:
        return self.values[:, self.names.index(name)]


def track_path(clips_dir: Path, clip_id: str) -> Path:
    """Where the animation track of clip ``clip_id`` lives."""
    return Path(clips_dir) / f"{clip_id}{TRACK_SUFFIX}"


def encode_track(
    *,
    clip_id: str,
    fps: int,
    blendshapes: Sequence[str],
    weights: np.ndarray,
    poses: np.ndarray | None,
    sample_rate: int,
    speech_start_s: float,
    avatar_sha256: str,
) -> bytes:
    """One clip's animation track, the exact per-frame values the renderer draws.

    Layout (little-endian): 8 magic bytes ``FLTRACK1``; a uint32, the byte length H of the
    JSON header; the header (UTF-8, padded with spaces so that 12 + H is a multiple of 4);
    then float32 values, frame after frame, ``n_channels`` per frame. Frame k is shown from
    t = k / fps seconds after the clip (and its audio) starts. Channels: the blendshapes the
    clip moves (``kind: blendshape``, weights 0-1, by target name) and, for a clip with head
    motion, :data:`POSE_CHANNELS` (``kind: pose``; degrees, ``neck_share`` a fraction).
    ``weights`` (n_frames, len(blendshapes)); ``poses`` (n_frames, 6) or None."""
    weights = np.asarray(weights, np.float32)
    n = len(weights)
    if weights.ndim != 2 or weights.shape[1] != len(blendshapes):
        raise FormatError(f"track {clip_id}: weights of shape {weights.shape} for "
                          f"{len(blendshapes)} blendshapes")  # fmt: skip
    channels = [{"name": b, "kind": "blendshape"} for b in blendshapes]
    columns = [weights]
    if poses is not None:
        poses = np.asarray(poses, np.float32)
        if poses.shape != (n, len(POSE_CHANNELS)):
            raise FormatError(f"track {clip_id}: poses of shape {poses.shape}, expected "
                              f"({n}, {len(POSE_CHANNELS)})")  # fmt: skip
        channels += [
            {"name": c, "kind": "pose", "unit": "fraction" if c == "neck_share" else "deg"}
            for c in POSE_CHANNELS
        ]
        columns.append(poses)
    header = {
        "format": TRACK_FORMAT,
        "clip_id": clip_id,
        "fps": fps,
        "n_frames": n,
        "frame_time": "frame k is shown from k / fps s after the clip starts",
        "channels": channels,
        "audio": {
            "sample_rate": sample_rate,
            "clip_start_sample": 0,
            "speech_start_s": speech_start_s,
            "speech_start_sample": round(speech_start_s * sample_rate),
        },
        "avatar_sha256": avatar_sha256,
    }
    text = json.dumps(header, ensure_ascii=False, sort_keys=True).encode("utf-8")
    text += b" " * (-(12 + len(text)) % 4)
    values = np.concatenate(columns, axis=1)
    body = np.ascontiguousarray(values, dtype="<f4").tobytes()
    return TRACK_MAGIC + struct.pack("<I", len(text)) + text + body


def decode_track(data: bytes, *, source: str = "track") -> Track:
    """A track from :func:`encode_track`'s bytes; FormatError naming ``source`` otherwise."""
    if len(data) < 12 or data[:8] != TRACK_MAGIC:
        raise FormatError(f"{source}: not a facelab animation track (no {TRACK_MAGIC.decode()})")
    (length,) = struct.unpack("<I", data[8:12])
    try:
        header = json.loads(data[12 : 12 + length].decode("utf-8"))
        n, c = int(header["n_frames"]), len(header["channels"])
    except (UnicodeDecodeError, ValueError, KeyError, TypeError):
        raise FormatError(f"{source}: the track's header is not readable") from None
    body = data[12 + length :]
    if header.get("format") != TRACK_FORMAT or len(body) != 4 * n * c:
        raise FormatError(
            f"{source}: expected {TRACK_FORMAT} with {n} frames x {c} channels "
            f"({4 * n * c} bytes of values), found {len(body)} bytes"
        )
    return Track(header, np.frombuffer(body, dtype="<f4").reshape(n, c).astype(np.float32))


def read_track(path: Path) -> Track:
    """The animation track in ``path`` (FormatError naming the file)."""
    try:
        data = Path(path).read_bytes()
    except OSError:
        raise FormatError(f"{path}: cannot read the animation track") from None
    return decode_track(data, source=str(path))


def behaviour_log_path(clips_dir: Path, clip_id: str) -> Path:
    """Where the behaviour event log of clip ``clip_id`` lives."""
    return Path(clips_dir) / f"{clip_id}{BEHAVIOUR_LOG_SUFFIX}"


def read_behaviour_log(path: Path) -> dict[str, Any]:
    """A behaviour event log: ``{"mode", "events": [{"unit", "layer", "start_s", "end_s",
    …}], "realisation": {…}}``. Raises :class:`FormatError` naming the file."""
    try:
        log = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError):
        raise FormatError(f"{path}: not a readable JSON behaviour log") from None
    events = log.get("events") if isinstance(log, dict) else None
    if not isinstance(events, list) or not all(
        isinstance(e, dict) and {"unit", "layer"} <= set(e) for e in events
    ):
        raise FormatError(f"{path}: a behaviour log has a list 'events' of units with layers")
    return log


def impression_header_problems(
    path: Path, *, expression: str | None = None, space: str | None = None
) -> Iterator[tuple[str, str]]:
    """What is wrong with an impression model file for a use: ``(key, message)`` pairs, the
    key ``model`` or ``expression``. Reads only the header (format, space, expressions)."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        yield "model", f"{path} was not found"
        return
    except (OSError, UnicodeDecodeError, ValueError):
        yield "model", f"{path}: not a readable JSON file"
        return
    if not isinstance(data, dict) or data.get("format") != IMPRESSION_FORMAT:
        yield "model", f"{path}: not a facelab impression model ({IMPRESSION_FORMAT})"
        return
    if space is not None and data.get("space") != space:
        yield (
            "model",
            f"{path}: a {data.get('space')}-space model; conditions need an ARKit-space model "
            "(render vertex-space models with facelab impression render)",
        )
    expressions = sorted(data.get("directions") or {})
    if expression is not None and expression not in expressions:
        yield (
            "expression",
            f"the model has no expression {expression!r}; it has {', '.join(expressions)}",
        )


def _earlier_rows(path: Path, columns: Sequence[str]) -> tuple[list[dict], list[str]]:
    """Rows of an existing manifest, and notes on what cannot be kept."""
    if not path.is_file():
        return [], []
    try:
        with open(path, newline="", encoding="utf-8") as fh:
            reader = csv.DictReader(fh)
            header = list(reader.fieldnames or [])
            rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as exc:
        aside = path.with_name("clips.csv.unreadable")
        path.replace(aside)
        return [], [f"{path}: cannot read the manifest there ({exc}); moved it to {aside.name}"]
    except OSError as exc:
        raise StageError(f"{path}: cannot read the existing manifest ({exc})") from exc
    if header != list(columns):
        return [], [
            f"{path.name} had other columns ({', '.join(header[:4])}, ...): "
            "its rows are replaced, not merged"
        ]
    return rows, []


def write_manifest(
    out: Path,
    rows: list[dict],
    *,
    columns: Sequence[str],
    merge: bool = False,
    provenance: str | None = None,
) -> list[str]:
    """Write ``out/clips.csv`` with ``rows`` (each a dict over ``columns``).

    With ``merge``, rows of the manifest already there are kept (before the new rows, in
    their order) when their clip is not among ``rows`` and their ``path`` still exists in
    ``out``. ``provenance`` names a column (e.g. the model's hash): kept rows whose value
    differs from the new rows' get a note. Returns notes for the user: what was kept, what
    was dropped and why.
    """
    path = out / MANIFEST_NAME
    notes: list[str] = []
    kept: list[dict] = []
    if merge:
        earlier, notes = _earlier_rows(path, columns)
        new_ids = {str(r["clip_id"]) for r in rows}
        gone = []
        for row in earlier:
            if row.get("clip_id") in new_ids:
                continue
            if not (out / str(row.get("path", ""))).is_file():
                gone.append(str(row.get("clip_id")))
                continue
            kept.append(row)
        if kept:
            notes.append(f"kept {len(kept)} clip(s) rendered earlier into {out} in clips.csv")
        if provenance and rows:
            now = {str(r[provenance]) for r in rows}
            other = [str(r["clip_id"]) for r in kept if r.get(provenance) not in now]
            if other:
                notes.append(
                    f"{len(other)} kept clip(s) have another {provenance} than these "
                    f"({', '.join(other[:5])}{', ...' if len(other) > 5 else ''}): "
                    "render into a new folder to keep them apart"
                )
        if gone:
            notes.append(
                f"dropped {len(gone)} earlier row(s) whose file is gone: {', '.join(gone)}"
            )
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(
            fh, fieldnames=list(columns), lineterminator="\n", extrasaction="ignore"
        )
        writer.writeheader()
        writer.writerows(kept)
        writer.writerows(rows)
    tmp.replace(path)
    return notes


def checks_failed(row: dict[str, str]) -> str:
    """The checks a ``clips.csv`` row's :data:`CHECKS_COLUMN` says failed on its clip and
    were not accepted (``"failed: modality"``), or ``""`` (passed, accepted, or not checked)."""
    value = str(row.get(CHECKS_COLUMN) or "")
    return value.split(";")[0] if value.startswith("failed") else ""
