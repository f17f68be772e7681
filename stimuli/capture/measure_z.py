"""Measure a Z matrix the paper's way from face-capture recordings.

Z[:, j] = mean over speakers of (mean over repetitions of (mean of the 52 ARKit coefficients
over the first ``window_s`` = 0.1 s after each onset of vowel j)).

Captures are CSV files, either

* **Live Link Face** (``Timecode, BlendShapeCount, EyeBlinkLeft, …``): PascalCase ARKit names,
  timecode ``HH:MM:SS:FF.fff`` at ``fps`` frames per second; or
* **generic**: a time column in seconds (``time``, ``time_s``, ``t`` or ``seconds``) and ARKit
  columns named in any case (``jawOpen``, ``JawOpen``, ``jaw_open`` is not accepted).

Onsets come from an onsets CSV (``capture, vowel, onset_s`` and optionally ``speaker``) or are
detected from an audio file recorded with each capture (same stem, e.g. ``s1.csv`` +
``s1.wav``, both starting at time 0) with the viseme analyser's voicing decision, given the
vowel sequence spoken.
"""

from __future__ import annotations

import csv
import math
import re
from collections import defaultdict
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.stimuli.arkit import ARKIT_NAMES, canonical_arkit_name
from facelab.stimuli.speech.track import VOWELS
from facelab.textfiles import read_rows

__all__ = [
    "Capture",
    "MeasuredZ",
    "detect_onsets",
    "measure_z",
    "read_capture",
    "read_onsets",
    "write_z",
]

TIME_COLUMNS = ("time", "time_s", "t", "seconds")
_TIMECODE = re.compile(r"^(\d+):(\d+):(\d+)[:;](\d+(?:\.\d+)?)$")


@dataclass(frozen=True)
class Capture:
    """times (N,) seconds from the capture start; coeffs (N, 52) in ARKit order."""

    path: Path
    times: np.ndarray
    coeffs: np.ndarray


@dataclass(frozen=True)
class MeasuredZ:
    z: np.ndarray  # (52, 5)
    spread: dict[str, dict]  # per vowel: repetitions, speakers, sd of the main rows


#: how far outside [0, 1] a capture's coefficient may lie (and be clipped) before it is an error
COEFF_SLACK = 0.01


def _parse_timecode(text: str, fps: float, where: str) -> float:
    m = _TIMECODE.match(text.strip())
    if not m:
        raise StageError(f"{where}: timecode {text!r} is not HH:MM:SS:FF(.fff)")
    h, mi, s, f = int(m.group(1)), int(m.group(2)), int(m.group(3)), float(m.group(4))
    return h * 3600 + mi * 60 + s + f / fps


def read_capture(path: Path | str, *, fps: float = 60.0) -> Capture:
    """Read a Live Link Face or generic capture CSV (see the module docstring)."""
    path = Path(path)
    table = read_rows(path, what="capture",
                      expected="a time column and the 52 ARKit coefficients")  # fmt: skip
    header = table.header
    if not table:
        raise StageError(f"capture {path}: a header and no rows of coefficients")
    rows = [[r[h] for h in header] for r in table]
    columns: dict[str, int] = {}
    for i, name in enumerate(header):
        canon = canonical_arkit_name(name)
        if canon in ARKIT_NAMES:
            columns.setdefault(canon, i)
    missing = [n for n in ARKIT_NAMES if n not in columns]
    if missing:
        raise StageError(
            f"{path}: missing ARKit columns: {', '.join(missing[:8])}"
            f"{' …' if len(missing) > 8 else ''} ({52 - len(missing)} of 52 found)"
        )
    lower = [h.strip().lower() for h in header]
    if "timecode" in lower:
        tcol = lower.index("timecode")
        times = [_parse_timecode(r[tcol], fps, f"{path}:{n}")
                 for n, r in zip(table.lines, rows, strict=True)]  # fmt: skip
    else:
        tcol = next((lower.index(c) for c in TIME_COLUMNS if c in lower), None)
        if tcol is None:
            raise StageError(
                f"{path}: no time column; expected Timecode (Live Link Face) or one of "
                f"{', '.join(TIME_COLUMNS)}"
            )
        times = [_number(r[tcol], at=f"{path}:{n}", what=header[tcol])
                 for n, r in zip(table.lines, rows, strict=True)]  # fmt: skip
    coeffs = np.array([
        [_number(r[columns[a]], at=f"{path}:{n}", what=header[columns[a]]) for a in ARKIT_NAMES]
        for n, r in zip(table.lines, rows, strict=True)
    ])  # fmt: skip
    t = np.asarray(times, dtype=float)
    if len(t) < 2:
        raise StageError(f"capture {path}: {len(t)} row of coefficients; expected a recording")
    if not np.all(np.diff(t) > 0):  # NaN fails too
        bad = int(np.argmin(np.diff(t) > 0)) + 1
        raise StageError(f"{path}:{table.lines[bad]}: times must increase from row to row")
    # ARKit coefficients lie in [0, 1]; trackers' rounding a hair outside is clipped
    outside = ~((coeffs >= -COEFF_SLACK) & (coeffs <= 1 + COEFF_SLACK))  # NaN is outside too
    if outside.any():
        r, c = np.argwhere(outside)[0]
        raise StageError(
            f"{path}:{table.lines[r]}: {ARKIT_NAMES[c]} is {coeffs[r, c]:g}; ARKit coefficients "
            "lie in [0, 1]"
        )
    coeffs = np.clip(coeffs, 0.0, 1.0)
    return Capture(path=path, times=t - t[0], coeffs=coeffs)


def _number(text: str, *, at: str, what: str) -> float:
    """A capture cell as a number, or a StageError naming the line and column."""
    try:
        return float(text)
    except ValueError:
        raise StageError(f"{at}: {what} is {text.strip()!r}, expected a number") from None


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (np.isfinite(value) and value >= 0):
        raise ValueError(f"onset_s is {text.strip()!r}, expected seconds >= 0")
    return value


def read_onsets(path: Path | str) -> list[dict]:
    """Onsets CSV rows: capture (file name or stem), vowel (a/i/u/e/o), onset_s, [speaker]."""
    path = Path(path)
    rows = read_rows(path, what="onsets", required=("capture", "vowel", "onset_s"),
                     expected="capture, vowel, onset_s and optionally speaker")  # fmt: skip
    out = []
    seen: dict[tuple[str, float], int] = {}
    for n, row in rows.located():
        try:
            vowel = row["vowel"].strip()
            if vowel not in VOWELS:
                raise StageError(f"{path}:{n}: vowel {vowel!r} is not one of a, i, u, e, o")
            out.append(
                {
                    "capture": Path(row["capture"].strip()).stem,
                    "vowel": vowel,
                    "onset_s": _seconds(row["onset_s"]),
                    "speaker": (row.get("speaker") or "").strip() or None,
                }
            )
        except ValueError as exc:
            raise StageError(f"{path}:{n}: {exc}") from None
        key = (out[-1]["capture"], out[-1]["onset_s"])
        if key in seen:
            raise StageError(f"{path}:{n}: the onset at {key[1]:g} s in capture {key[0]!r} is "
                             f"listed twice (line {seen[key]} too)")  # fmt: skip
        seen[key] = n
    return out


def detect_onsets(audio: Path, *, vowels: str) -> list[dict]:
    """Onsets of the voiced segments in a capture's audio, labelled with ``vowels`` in order."""
    from facelab.stimuli.speech.analyser import analyze
    from facelab.stimuli.speech.audio import load_audio
    from facelab.stimuli.speech.vowels import vowel_segments

    speech = load_audio(audio, sample_rate=48_000)
    track = analyze(speech.samples, sample_rate=speech.sample_rate).compensated()
    segs = vowel_segments(track)
    if len(segs) != len(vowels):
        raise StageError(
            f"{audio}: found {len(segs)} voiced segments, expected {len(vowels)} "
            f"({vowels}); give onsets in a CSV instead"
        )
    return [
        {"capture": audio.stem, "vowel": v, "onset_s": float(track.times[a]), "speaker": None}
        for (a, _), v in zip(segs, vowels, strict=True)
    ]


def measure_z(
    captures: Sequence[Capture], onsets: Sequence[dict], *, window_s: float = 0.1
) -> MeasuredZ:
    """Z from captures and labelled onsets (see the module docstring)."""
    by_stem = {c.path.stem: c for c in captures}
    per: dict[tuple[str, str], list[np.ndarray]] = defaultdict(list)
    for onset in onsets:
        cap = by_stem.get(onset["capture"])
        if cap is None:
            raise StageError(f"onset for capture {onset['capture']!r}, which was not given")
        sel = (cap.times >= onset["onset_s"]) & (cap.times < onset["onset_s"] + window_s)
        if not sel.any():
            raise StageError(
                f"{cap.path}: no frames in {window_s:g} s after onset "
                f"{onset['onset_s']:g} s ({onset['vowel']})"
            )
        speaker = onset["speaker"] or onset["capture"]
        per[(speaker, onset["vowel"])].append(cap.coeffs[sel].mean(axis=0))
    z = np.zeros((len(ARKIT_NAMES), len(VOWELS)))
    spread: dict[str, dict] = {}
    for j, vowel in enumerate(VOWELS):
        speakers = sorted({s for s, v in per if v == vowel})
        if not speakers:
            raise StageError(f"no onsets for vowel {vowel!r}; every vowel needs at least one")
        speaker_means = np.stack([np.mean(per[(s, vowel)], axis=0) for s in speakers])
        z[:, j] = speaker_means.mean(axis=0)
        reps = np.stack([r for s in speakers for r in per[(s, vowel)]])
        top = np.argsort(z[:, j])[::-1][:5]
        spread[vowel] = {
            "repetitions": len(reps),
            "speakers": len(speakers),
            "main_rows": {
                ARKIT_NAMES[i]: {
                    "mean": round(float(z[i, j]), 4),
                    "sd_repetitions": round(
                        float(reps[:, i].std(ddof=1)) if len(reps) > 1 else 0.0, 4
                    ),
                    "sd_speakers": round(
                        float(speaker_means[:, i].std(ddof=1)) if len(speakers) > 1 else 0.0, 4
                    ),
                }
                for i in top
            },
        }
    return MeasuredZ(z=np.clip(z, 0.0, 1.0), spread=spread)


def write_z(path: Path, z: np.ndarray) -> None:
    """Write Z in the format ``facelab.stimuli.capture.zmatrix.load_z`` reads."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(["blendshape", *VOWELS])
        for name, row in zip(ARKIT_NAMES, z, strict=True):
            writer.writerow([name, *[f"{v:.6g}" for v in row]])
