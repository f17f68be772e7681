"""Animation tracks made outside facelab, read into one shape: frame times (s) and named
blendshape weights (ARKit camelCase or ``viseme_*``), for ``method: external_track``.

Formats (``format: auto`` tells them apart by extension and content):

* ``live_link_face`` - Live Link Face CSV (Epic's iPhone app): ``Timecode`` as
  ``HH:MM:SS:FF`` or ``HH:MM:SS:FF.mmm`` (frame and fraction), ``BlendShapeCount``, the 52
  ARKit names in PascalCase, then head and eye angles (``HeadYaw`` …, kept in ``angles``:
  ``method: external_track`` plays them as the clip's head pose). ``FF.fff`` is the timecode
  frame and its fraction (a 60 fps capture on a 30 fps timecode: .000 and .500); the
  timecode's rate is read from the frame number before a second rolls over, or given as
  ``fps`` (needed for a capture shorter than a second); the capture's own rate follows;
* ``arkit_json`` - JSON frames: a list, or ``{"fps": F, "frames": [...]}``; each frame a
  mapping of ARKit names to weights, or ``{"time": s, "blendshapes": {...}}`` (``t``,
  ``timestamp`` and ``weights`` are read too). Names a frame leaves out are 0 in it;
* ``audio2face`` - NVIDIA Audio2Face(-3D)'s blendshape export: ``exportFps``, ``facsNames``,
  ``weightMat`` (frames x names);
* ``viseme_csv`` - Oculus LipSync / uLipSync visemes: a time column (``time``, ``time_s``,
  ``t`` or ``timestamp``, seconds) and the 15 Oculus visemes (``sil PP FF TH DD kk CH SS nn RR
  aa E ih oh ou``, with or without ``viseme_``), played through the avatar's viseme targets;
* ``gltf`` - a glTF/GLB file's morph-weight animation (the first animation channel whose path
  is ``weights``; LINEAR or STEP samplers; target names from the mesh's ``targetNames``).

Names are matched case-insensitively (``JawOpen``, ``jaw_open`` is not ARKit and is an error);
a column facelab does not know is an error naming it, as are missing ARKit or viseme columns of
a tabular format. Errors name the file and, for CSV, the line. Pure numpy and the standard
library (glTF through :mod:`facelab.stimuli.avatar.gltf`).
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.stimuli.arkit import ARKIT_NAMES, OCULUS_VISEMES, VISEME_TARGETS, canonical_arkit_name
from facelab.textfiles import read_rows

__all__ = ["FORMATS", "CapturedTrack", "detect_format", "read_capture", "resample"]

FORMATS = ("live_link_face", "arkit_json", "audio2face", "viseme_csv", "gltf")
#: Live Link Face's columns that are not blendshapes (head and eye angles, the count)
_LLF_EXTRA = {
    "timecode", "blendshapecount", "headyaw", "headpitch", "headroll", "lefteyeyaw",
    "lefteyepitch", "lefteyeroll", "righteyeyaw", "righteyepitch", "righteyeroll",
}  # fmt: skip
_TIME_COLUMNS = ("time", "time_s", "t", "timestamp", "seconds")
_RATES = (24.0, 25.0, 30.0, 48.0, 50.0, 60.0, 120.0)


@dataclass(frozen=True)
class CapturedTrack:
    """times (T,) s from the capture's start, increasing; weights (T, K); names (K,) facelab
    target names; ``angles`` {name: (T,)} head/eye angles read but not played; ``fps`` the
    capture's frame rate when the file gives one; ``notes`` facts for the clip's JSON."""

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...]
    format: str
    fps: float | None = None
    angles: dict[str, np.ndarray] = field(default_factory=dict)
    notes: dict = field(default_factory=dict)


def _bad(path: Path, message: str) -> StageError:
    return StageError(f"{path}: {message}")


def detect_format(path: Path) -> str:
    """The format of ``path`` from its extension and first bytes (see the module docstring)."""
    suffix = path.suffix.lower()
    if suffix in (".glb", ".gltf"):
        return "gltf"
    if suffix == ".json":
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise _bad(path, f"not readable JSON ({_why(exc)})") from None
        if isinstance(data, dict) and "weightMat" in data:
            return "audio2face"
        return "arkit_json"
    if suffix == ".csv":
        head = _csv_header(path)
        if any(h.strip().lower() == "timecode" for h in head):
            return "live_link_face"
        return "viseme_csv"
    raise _bad(path, "expected a .csv, .json, .glb or .gltf track file")


def _why(exc: Exception) -> str:
    if isinstance(exc, json.JSONDecodeError):
        return f"line {exc.lineno}: {exc.msg}"
    if isinstance(exc, UnicodeDecodeError):
        return "not UTF-8 text"
    return "cannot be read"


def _csv_header(path: Path) -> list[str]:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise _bad(path, _why(exc)) from None
    first = text.splitlines()[0] if text.strip() else ""
    if not first:
        raise _bad(path, "the file is empty: expected a header line")
    return next(csv.reader([first]))


def _csv_rows(path: Path) -> tuple[list[str], list[list[str]], list[int]]:
    """The header, the frames' fields and each frame's line (the strict table reader: a
    row with a field too many or too few is refused at its line)."""
    table = read_rows(path)
    if not table:
        raise _bad(path, "expected a header line and at least one frame")
    return table.header, [[r[h] for h in table.header] for r in table], table.lines


def _numbers(
    path: Path, rows: list[list[str]], cols: list[int], header: list[str], lines: list[int]
) -> np.ndarray:
    out = np.zeros((len(rows), len(cols)))
    for i, row in enumerate(rows):
        for j, c in enumerate(cols):
            try:
                out[i, j] = float(row[c])
            except ValueError:
                raise _bad(path, f"line {lines[i]}, column {header[c]!r}: {row[c]!r} is not a "
                           "number") from None  # fmt: skip
    if not np.isfinite(out).all():
        i = int(np.argwhere(~np.isfinite(out))[0][0])
        raise _bad(path, f"line {lines[i]}: a value is not finite")
    return out


def _named(path: Path, header: list[str], skip: set[str], *, kind: str) -> dict[int, str]:
    """{column: facelab target name} for every column not in ``skip``; unknown names and, for
    ``kind`` arkit/viseme, missing ones are errors."""
    found, unknown = {}, []
    for c, raw in enumerate(header):
        key = raw.strip()
        if not key or key.lower() in skip:
            continue
        name = canonical_arkit_name(key)
        if name is None and kind == "viseme":
            name = canonical_arkit_name(f"viseme_{key}")
        if name is None:
            unknown.append(key)
        else:
            found[c] = name
    if unknown:
        expected = {"arkit": "ARKit blendshape names (e.g. JawOpen)",
                    "viseme": f"the Oculus visemes {' '.join(OCULUS_VISEMES)}"}.get(
            kind, "ARKit blendshape or viseme_* names")  # fmt: skip
        raise _bad(path, f"unknown channel(s) {', '.join(unknown[:8])}; expected {expected}")
    if kind not in ("arkit", "viseme"):
        return found
    want = ARKIT_NAMES if kind == "arkit" else VISEME_TARGETS
    missing = [n for n in want if n not in found.values()]
    if missing:
        raise _bad(path, f"missing channel(s) {', '.join(missing[:8])}"
                   + (f" and {len(missing) - 8} more" if len(missing) > 8 else ""))  # fmt: skip
    return found


_TIMECODE = re.compile(r"^(\d+):(\d{1,2}):(\d{1,2})[:;](\d{1,3})(?:\.(\d+))?$")


def _live_link_face(path: Path, *, fps: float | None) -> CapturedTrack:
    header, rows, lines = _csv_rows(path)
    lower = [h.strip().lower() for h in header]
    tc = lower.index("timecode")
    parts = []
    for i, row in enumerate(rows):
        m = _TIMECODE.match(row[tc].strip()) if tc < len(row) else None
        if m is None:
            cell = row[tc] if tc < len(row) else "(missing)"
            raise _bad(path, f"line {i + 2}: Timecode {cell!r} is not HH:MM:SS:FF[.mmm]")
        h, mi, s, f, frac = m.groups()
        parts.append((int(h) * 3600 + int(mi) * 60 + int(s), int(f),
                      float(f"0.{frac}") if frac else 0.0))  # fmt: skip
    note = "given"
    if fps is None:
        rolls = [parts[i - 1][1] + 1 for i in range(1, len(parts))
                 if parts[i][0] == parts[i - 1][0] + 1 and parts[i][1] == 0]  # fmt: skip
        if rolls:
            fps, note = float(max(rolls)), "from the timecode's rollover"
        else:
            top = max(p[1] for p in parts) + 1
            fps = next((r for r in _RATES if r >= top), float(top))
            note = f"no second rolls over: the smallest common rate above frame {top - 1}"
    sec = np.array([p[0] + (p[1] + p[2]) / fps for p in parts])
    times = sec - sec[0]
    if np.any(np.diff(times) <= 0):
        i = int(np.argmax(np.diff(times) <= 0)) + 1
        raise _bad(path, f"line {i + 2}: the Timecode does not advance")
    found = _named(path, header, _LLF_EXTRA, kind="arkit")
    cols = list(found)
    weights = _numbers(path, rows, cols, header, lines)
    angle_names = _LLF_EXTRA - {"timecode", "blendshapecount"}
    angle_cols = [c for c, h in enumerate(lower) if h in angle_names]
    angles = dict(zip((header[c].strip() for c in angle_cols),
                      _numbers(path, rows, angle_cols, header, lines).T, strict=True))  # fmt: skip
    capture_fps = float(round(1.0 / float(np.median(np.diff(times))), 2)) if len(times) > 1 \
        else fps  # fmt: skip
    notes = {"timecode_fps": fps, "timecode_fps_source": note, "capture_fps": capture_fps}
    return CapturedTrack(times, weights, tuple(found[c] for c in cols), "live_link_face",
                         capture_fps, angles, notes)  # fmt: skip


def _viseme_csv(path: Path) -> CapturedTrack:
    header, rows, lines = _csv_rows(path)
    lower = [h.strip().lower() for h in header]
    time_col = next((lower.index(t) for t in _TIME_COLUMNS if t in lower), None)
    if time_col is None:
        raise _bad(path, f"no time column: expected one of {', '.join(_TIME_COLUMNS)} (seconds)")
    found = _named(path, header, {lower[time_col]}, kind="viseme")
    cols = list(found)
    times = _numbers(path, rows, [time_col], header, lines)[:, 0]
    _increasing(path, times, first_line=2)
    return CapturedTrack(times - times[0], _numbers(path, rows, cols, header, lines),
                         tuple(found[c] for c in cols), "viseme_csv")  # fmt: skip


def _increasing(path: Path, times: np.ndarray, *, first_line: int | None = None) -> None:
    bad = np.nonzero(np.diff(times) <= 0)[0]
    if len(bad):
        where = f"line {bad[0] + 1 + first_line}: " if first_line else f"frame {bad[0] + 1}: "
        raise _bad(path, f"{where}times must increase")


def _arkit_json(path: Path, data: object, *, fps: float | None) -> CapturedTrack:
    frames = data.get("frames") if isinstance(data, dict) else data
    rate = data.get("fps", fps) if isinstance(data, dict) else fps
    if not isinstance(frames, list) or not frames:
        raise _bad(path, 'expected a list of frames or {"fps": F, "frames": [...]}')
    times, rows, names = [], [], {}
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict):
            raise _bad(path, f"frame {i}: expected a mapping of names to weights")
        t = next((frame[k] for k in ("time", "t", "timestamp") if k in frame), None)
        shapes = frame.get("blendshapes", frame.get("weights", frame))
        if not isinstance(shapes, dict):
            raise _bad(path, f"frame {i}: blendshapes must be a mapping of names to weights")
        row = {}
        for key, value in shapes.items():
            if key in ("time", "t", "timestamp"):
                continue
            name = canonical_arkit_name(str(key))
            if name is None:
                raise _bad(path, f"frame {i}: unknown channel {key!r}; expected ARKit names")
            if isinstance(value, bool) or not isinstance(value, (int, float)) or \
                    not np.isfinite(value):  # fmt: skip
                raise _bad(path, f"frame {i}: {key} is {value!r}, expected a number")
            row[name] = float(value)
            names.setdefault(name, None)
        if t is None:
            if rate is None:
                raise _bad(path, f'frame {i} has no "time" and the file no "fps"')
            t = i / float(rate)
        if isinstance(t, bool) or not isinstance(t, (int, float)):
            raise _bad(path, f"frame {i}: time {t!r} is not a number of seconds")
        times.append(float(t))
        rows.append(row)
    order = tuple(names)
    weights = np.array([[r.get(n, 0.0) for n in order] for r in rows])
    times_a = np.array(times)
    _increasing(path, times_a)
    return CapturedTrack(times_a - times_a[0], weights.reshape(len(rows), len(order)), order,
                         "arkit_json", float(rate) if rate else None)  # fmt: skip


def _audio2face(path: Path, data: dict) -> CapturedTrack:
    try:
        fps = float(data["exportFps"])
        names = [str(n) for n in data["facsNames"]]
        mat = np.asarray(data["weightMat"], dtype=float)
    except (KeyError, TypeError, ValueError):
        raise _bad(path, "an Audio2Face export needs exportFps, facsNames and weightMat "
                   "(frames x names) of numbers") from None  # fmt: skip
    if mat.ndim != 2 or mat.shape[1] != len(names) or not len(mat):
        raise _bad(path, f"weightMat is {mat.shape}, expected (frames, {len(names)})")
    if not np.isfinite(mat).all() or fps <= 0:
        raise _bad(path, "weightMat holds a value that is not finite, or exportFps <= 0")
    found = _named(path, names, set(), kind="arkit")
    cols = list(found)
    return CapturedTrack(np.arange(len(mat)) / fps, mat[:, cols],
                         tuple(found[c] for c in cols), "audio2face", fps)  # fmt: skip


def _gltf(path: Path) -> CapturedTrack:
    from facelab.errors import AvatarError
    from facelab.stimuli.avatar.gltf import accessor, open_gltf

    try:
        doc, buffers = open_gltf(path)
    except AvatarError as exc:
        raise StageError(str(exc)) from None
    for anim in doc.animations or []:
        for ch in anim.channels or []:
            if ch.target is None or ch.target.path != "weights" or ch.target.node is None:
                continue
            node = doc.nodes[ch.target.node]
            mesh = doc.meshes[node.mesh] if node.mesh is not None else None
            extras = mesh.extras if mesh is not None and isinstance(mesh.extras, dict) else {}
            names = [str(n) for n in extras.get("targetNames", [])]
            sampler = anim.samplers[ch.sampler]
            times = accessor(doc, buffers, sampler.input).astype(float).reshape(-1)
            values = accessor(doc, buffers, sampler.output).astype(float).reshape(-1)
            n_t = len(names) or (len(values) // max(len(times), 1))
            if sampler.interpolation == "CUBICSPLINE":  # in-tangent, value, out-tangent
                values = values.reshape(len(times), 3, n_t)[:, 1, :]
            values = values.reshape(len(times), n_t)
            if not names:
                raise _bad(path, "the animated mesh has no targetNames: its weights cannot "
                           "be named")  # fmt: skip
            found = _named(path, names, set(), kind="any")
            _increasing(path, times)
            cols = list(found)
            return CapturedTrack(times - times[0], values[:, cols],
                                 tuple(found[c] for c in cols), "gltf")  # fmt: skip
    raise _bad(path, "no animation channel of morph-target weights in the file")


def read_capture(path: Path, *, format: str = "auto", fps: float | None = None) -> CapturedTrack:
    """The track in ``path`` (see the module docstring); StageError naming the file (and
    line) when it cannot be used."""
    path = Path(path)
    if not path.is_file():
        raise _bad(path, "the track file was not found")
    kind = detect_format(path) if format == "auto" else format
    if kind not in FORMATS:
        raise _bad(path, f"unknown format {kind!r}; expected auto or {', '.join(FORMATS)}")
    if kind == "live_link_face":
        track = _live_link_face(path, fps=fps)
    elif kind == "viseme_csv":
        track = _viseme_csv(path)
    elif kind == "gltf":
        track = _gltf(path)
    else:
        try:
            data = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise _bad(path, f"not readable JSON ({_why(exc)})") from None
        if kind == "audio2face":
            if not isinstance(data, dict):
                raise _bad(path, "an Audio2Face export is a JSON object")
            track = _audio2face(path, data)
        else:
            track = _arkit_json(path, data, fps=fps)
    if track.weights.size and (track.weights.min() < -0.01 or track.weights.max() > 1.01):
        lo, hi = float(track.weights.min()), float(track.weights.max())
        raise _bad(path, f"weights run from {lo:.3g} to {hi:.3g}; expected 0-1 "
                   "(blendshape weights)")  # fmt: skip
    return track


def resample(track: CapturedTrack, times: np.ndarray, *, offset_s: float = 0.0) -> np.ndarray:
    """(len(times), K) the capture's weights at ``times`` (s of the stimulus), the capture
    shifted by ``offset_s`` (positive: the capture starts later), linear between frames and
    held at its first and last frame outside them; clipped to [0, 1]."""
    t = np.asarray(times, float) - offset_s
    out = np.empty((len(t), len(track.names)))
    for k in range(len(track.names)):
        out[:, k] = np.interp(t, track.times, track.weights[:, k])
    return np.clip(out, 0.0, 1.0)
