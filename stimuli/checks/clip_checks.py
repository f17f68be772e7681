"""Checks of rendered clips from what an outside face tracker measured on their frames
(:class:`~facelab.stimuli.checks.face_tracker.ClipTracking`) and from their audio - pure
functions of arrays, no rendering and no tracker here.

* ``face_visible``: detection confidence per frame (minimum and median), frames without a
  face, the face box inside the frame and its height;
* ``articulation``: inner-lip aperture and mouth width at each vowel's peak, held to the
  Japanese vowel rules (あ opens most, う least, い is widest) and the protocol's own rules;
* ``av_sync``: the lag of the tracked mouth opening behind the audio envelope, by
  cross-correlation (independent of the track's own timestamps);
* ``conditions_differ`` and ``levels``: frame differences over the face region between
  clips.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence

import numpy as np
import scipy.fft as sfft

from facelab.stimuli.checks.face_tracker import ClipTracking
from facelab.stimuli.checks.rows import CheckRow, at_least, at_most, info

__all__ = [
    "DETECTION_MEDIAN",
    "DETECTION_MIN",
    "FACE_DIFFERENCE",
    "FACE_HEIGHT_MIN",
    "MAX_LAG_FRAMES",
    "articulation_rows",
    "av_sync_rows",
    "difference_rows",
    "envelope",
    "face_difference",
    "face_visible_rows",
    "lag_is_identifiable",
    "level_rows",
    "mix_lag",
    "mouth_at_peaks",
    "noise_rows",
    "not_measured",
    "picture_lag",
    "sync_lag",
    "too_small",
]

#: face detection (MediaPipe, short range): every frame at least DETECTION_MIN, half of them at
#: least DETECTION_MEDIAN
DETECTION_MIN = 0.5
DETECTION_MEDIAN = 0.8
#: the face (forehead 10 to chin 152) at least this share of the frame's height
FACE_HEIGHT_MIN = 0.15
#: grey levels (0-255) of :func:`face_difference` from which two clips count as different:
#: the most-changed 1/64 of the face changes by 2 grey levels or more in 5 % of the frames
FACE_DIFFERENCE = 2.0
#: the mouth may lag or lead the sound by at most this many frames
MAX_LAG_FRAMES = 1.0
#: lags searched by cross-correlation either side (beyond a clip's intended offset)
MAX_SEARCH_FRAMES = 8
#: frames either side of a vowel's peak that are measured (±0.1 s at 30 fps)
PEAK_HALF_WINDOW_S = 0.1
#: the lips are read only on faces at least this tall (forehead to chin, pixels of the clip as
#: rendered): smaller, the tracker's mouth landmarks are guesses (the default head at 160x90 is
#: 45 px tall and "opens" お wider than あ); articulation and sync are then not measured (warning)
MIN_FACE_PX = 80
#: the vowel rules compare medians of tracked measures that jitter: on a still face the
#: tracker's mouth width varies by 1.1 % (SD over frames); a rule holds within 2 %
RULE_TOLERANCE = 0.02


def too_small(tr: ClipTracking, *, clip_height: int) -> str | None:
    """Why the lips of this clip cannot be read (face under :data:`MIN_FACE_PX`), or None."""
    if not np.isfinite(tr.face_height).any():
        return "the face mesh found no face"
    px = float(np.nanmedian(tr.face_height)) * clip_height
    if px < MIN_FACE_PX:
        return (f"the face is {px:.0f} px tall in this clip; the tracker reads lips from "
                f"{MIN_FACE_PX} px: render larger (--size) to check it")  # fmt: skip
    return None


def too_few_frames(peak_times: Sequence[float], *, fps: float) -> str | None:
    """Why a clip's frames cannot show each vowel of a stimulus at its peak (a frame every
    1/fps s, against vowels closer than two frames apart: the frame nearest one vowel's peak
    may show its neighbour, as at 10 fps in あいうえお spoken without pauses), or None."""
    gaps = np.diff(np.sort(np.asarray(peak_times, float)))
    gap = float(gaps.min()) if len(gaps) else math.inf
    if 2.0 / fps <= gap + 1e-6:
        return None
    return (f"its vowels peak {1000 * gap:.0f} ms apart and the clip shows a frame every "
            f"{1000 / fps:.0f} ms: render at {math.ceil(2.0 / gap - 1e-3)} fps or more "
            "(--fps) to check them")  # fmt: skip


def not_measured(*, clip: str, condition: str, check: str, why: str) -> CheckRow:
    """A warning row: the check could not be made on this clip."""
    return CheckRow(clip, condition, check, "not_measured", math.nan, "measurable", False, why,
                    "warning")  # fmt: skip


def face_visible_rows(tr: ClipTracking, *, clip: str, condition: str) -> list[CheckRow]:
    """Detection confidence (min, median), frames without a face, framing."""
    kw = {"clip": clip, "condition": condition, "check": "face_visible"}
    det = tr.detection
    worst = int(np.argmin(det)) if len(det) else 0
    rows = [
        at_least(DETECTION_MIN, float(det.min()) if len(det) else None,
                 measure="detection_min", note=f"lowest at frame {worst}", **kw),
        at_least(DETECTION_MEDIAN, float(np.median(det)) if len(det) else None,
                 measure="detection_median", **kw),
        at_most(0, int((det < 0.1).sum()), measure="frames_without_face", **kw),
    ]  # fmt: skip
    box = tr.box[~np.isnan(tr.box).any(axis=1)]
    if len(box):
        margin = np.minimum.reduce([box[:, 0], box[:, 1], 1 - box[:, 2], 1 - box[:, 3]])
        rows.append(at_least(0.0, float(margin.min()), measure="face_box_margin_min",
                             note="the face mesh's box to the frame's nearest edge, in frame "
                             "sizes (negative: cut off)", **kw))  # fmt: skip
    else:
        rows.append(at_least(0.0, None, measure="face_box_margin_min",
                             note="the face mesh found no face", **kw))  # fmt: skip
    height = np.nanmedian(tr.face_height) if np.isfinite(tr.face_height).any() else None
    rows.append(at_least(FACE_HEIGHT_MIN, height, measure="face_height_median",
                         note="forehead to chin over the frame's height", **kw))  # fmt: skip
    return rows


#: a muted clip's loudest sample (-60 dBFS) and a voiced clip's least RMS (-50 dBFS)
MUTED_PEAK = 1e-3
VOICED_RMS = 10 ** (-50 / 20)
#: a still face's tracked lip opening may vary this much (face heights, 5th to 95th centile)
STILL_APERTURE = 0.01


def modality_rows(
    tr: ClipTracking, sound: np.ndarray, *, modality: str, face: str, clip: str, condition: str
) -> list[CheckRow]:
    """What a condition's modality promises, measured on the clip (``check`` modality): a
    visual_only clip is silent; an audio_only clip has the voice and a face that does not
    move (``face`` still) or no face at all (``face`` none). Audiovisual: no rows (the
    face_visible, articulation and av_sync checks cover it)."""
    kw = {"clip": clip, "condition": condition, "check": "modality"}
    if modality == "visual_only":
        peak = float(np.abs(sound).max()) if len(sound) else 0.0
        return [at_most(MUTED_PEAK, peak, measure="audio_peak", note="visual_only: muted "
                        "(the loudest sample, full scale 1)", **kw)]  # fmt: skip
    if modality != "audio_only":
        return []
    rms = float(np.sqrt(np.mean(np.square(sound, dtype=np.float64)))) if len(sound) else 0.0
    rows = [at_least(VOICED_RMS, rms, measure="audio_rms", note="audio_only: the voice is "
                     "heard", **kw)]  # fmt: skip
    if face == "none":
        found = float(tr.detection.max()) if len(tr.detection) else 0.0
        rows.append(at_most(DETECTION_MIN, found, measure="face_detection_max",
                            note="audio_only without a face: no face is found", **kw))  # fmt: skip
        return rows
    rel = tr.aperture[np.isfinite(tr.aperture)]  # (already in face heights)
    spread = float(np.percentile(rel, 95) - np.percentile(rel, 5)) if len(rel) else None
    rows.append(at_most(STILL_APERTURE, spread, measure="aperture_spread",
                        note="audio_only: the still face's lip opening, 5th to 95th centile, "
                        "in face heights", **kw))  # fmt: skip
    return rows


def mouth_at_peaks(
    tr: ClipTracking, peaks: Sequence[tuple[str, float]], *, fps: float, offset_s: float
) -> dict[str, dict[str, float]]:
    """{vowel: {"aperture", "width"}}: the median over the frames within ±0.1 s of each of the
    vowel's peaks (``peaks`` (vowel, s from the speech's start); the clip's speech starts at
    ``offset_s``). NaN where the mesh found no face."""
    out: dict[str, dict[str, list[float]]] = {}
    for vowel, t in peaks:
        lo = max(0, math.floor((t + offset_s - PEAK_HALF_WINDOW_S) * fps + 0.5))
        hi = min(tr.frames, math.floor((t + offset_s + PEAK_HALF_WINDOW_S) * fps + 0.5) + 1)
        got = out.setdefault(vowel, {"aperture": [], "width": []})
        got["aperture"] += list(tr.aperture[lo:hi])
        got["width"] += list(tr.width[lo:hi])
    return {
        v: {k: float(np.nanmedian(x)) if np.isfinite(x).any() else math.nan for k, x in m.items()}
        for v, m in out.items()
    }


#: the default Japanese vowel rules: (name, measure, vowel, "largest" | "smallest")
VOWEL_RULES = (
    ("a_largest_aperture", "aperture", "a", "largest"),
    ("u_smallest_aperture", "aperture", "u", "smallest"),
    ("i_widest_mouth", "width", "i", "largest"),
)


def articulation_rows(
    mouths: Mapping[str, Mapping[str, Mapping[str, float]]],
    *,
    clips: Mapping[str, str],
    vowel_rules: bool,
    rules: Sequence[object] = (),
) -> list[CheckRow]:
    """``mouths`` {condition: {vowel: {aperture, width}}} of one stimulus, ``clips``
    {condition: clip id}. Rows: each vowel's measures (info), the vowel rules per condition
    (the ratio of the vowel's measure to the largest other - or of the smallest other to it -
    at least 1 less :data:`RULE_TOLERANCE`), and the protocol's rules (the ratio between
    conditions)."""
    rows: list[CheckRow] = []
    for cond, vowels in mouths.items():
        kw = {"clip": clips[cond], "condition": cond, "check": "articulation"}
        for vowel, m in vowels.items():
            for measure in ("aperture", "width"):
                rows.append(info(m[measure], measure=f"{measure}:{vowel}", **kw))
        if not vowel_rules:
            continue
        for name, measure, vowel, how in VOWEL_RULES:
            others = {v: m[measure] for v, m in vowels.items() if v != vowel}
            if vowel not in vowels or not others:
                continue
            mine = vowels[vowel][measure]
            if how == "largest":
                rival = max(others, key=lambda v: others[v])
                ratio = mine / others[rival] if others[rival] > 0 else math.nan
                note = f"{vowel} {mine:.4f} against {rival} {others[rival]:.4f}"
            else:
                rival = min(others, key=lambda v: others[v])
                ratio = others[rival] / mine if mine > 0 else math.nan
                note = f"{vowel} {mine:.4f} against {rival} {others[rival]:.4f}"
            rows.append(at_least(1.0 - RULE_TOLERANCE, ratio, measure=name, note=note, **kw))
    for rule in rules:
        a = mouths.get(rule.condition, {}).get(rule.vowel)  # type: ignore[attr-defined]
        b = mouths.get(rule.relative_to, {}).get(rule.vowel)  # type: ignore[attr-defined]
        if a is None or b is None:
            continue
        num, den = a[rule.measure], b[rule.measure]  # type: ignore[attr-defined]
        ratio = num / den if den > 0 else math.nan
        rows.append(at_least(
            rule.at_least, ratio, clip=clips[rule.condition], condition=rule.condition,  # type: ignore[attr-defined]
            check="articulation",
            measure=f"{rule.measure}:{rule.vowel} {rule.condition}/{rule.relative_to}",  # type: ignore[attr-defined]
            note=f"{num:.4f} against {den:.4f}",
        ))  # fmt: skip
    return rows


def envelope(samples: np.ndarray, *, sample_rate: int, fps: float, n_frames: int) -> np.ndarray:
    """(n_frames,) the audio's level while each video frame is shown (frame k from k / fps s):
    RMS in dB, floored 50 dB below the loudest frame. ``samples`` (n,) mono."""
    edges = np.round(np.arange(n_frames + 1) * sample_rate / fps).astype(int)
    x = np.asarray(samples, np.float64) ** 2
    csum = np.concatenate([[0.0], np.cumsum(x)])
    edges = np.clip(edges, 0, len(x))
    power = (csum[edges[1:]] - csum[edges[:-1]]) / np.maximum(edges[1:] - edges[:-1], 1)
    db = 10 * np.log10(power + 1e-12)
    return np.maximum(db, db.max() - 50.0)


def sync_lag(sound: np.ndarray, mouth: np.ndarray, *, max_lag: int = 8) -> tuple[float, float]:
    """(lag in frames, correlation at that lag): how many frames the mouth opening follows the
    sound (negative: it leads), the peak of the normalised cross-correlation within
    ±``max_lag`` refined by a parabola. NaN in ``mouth`` is filled by interpolation."""
    m = np.asarray(mouth, float).copy()
    ok = np.isfinite(m)
    if ok.sum() < 10:
        return math.nan, math.nan
    m[~ok] = np.interp(np.nonzero(~ok)[0], np.nonzero(ok)[0], m[ok])
    s = np.asarray(sound, float)
    n = min(len(s), len(m))
    s, m = s[:n], m[:n]
    lags = np.arange(-max_lag, max_lag + 1)
    corr = []
    for lag in lags:
        a, b = (s[: n - lag], m[lag:]) if lag >= 0 else (s[-lag:], m[: n + lag])
        if np.std(a) == 0 or np.std(b) == 0:
            corr.append(0.0)
            continue
        corr.append(float(np.corrcoef(a, b)[0, 1]))
    c = np.asarray(corr)
    k = int(np.argmax(c))
    shift = 0.0
    if 0 < k < len(c) - 1:
        denom = c[k - 1] - 2 * c[k] + c[k + 1]
        shift = 0.5 * (c[k - 1] - c[k + 1]) / denom if denom < 0 else 0.0
    return float(lags[k] + shift), float(c[k])


def _track_fit(
    track_values: np.ndarray, mouth: np.ndarray
) -> tuple[np.ndarray, Callable[[int], tuple[np.ndarray, float]]] | None:
    """(the tracked opening, fit(shift) -> (fitted opening, R²)): the track's channels (n, K)
    reduced to their first three principal components and fitted by least squares to the
    opening with the picture ``shift`` frames behind. None without enough tracked frames."""
    m = np.asarray(mouth, float)
    x = np.asarray(track_values, float)
    n = min(len(m), len(x))
    m, x = m[:n], x[:n]
    ok = np.isfinite(m)
    if x.ndim != 2 or ok.sum() < 20:
        return None
    x = x - x.mean(axis=0)
    u, sv, _ = np.linalg.svd(x, full_matrices=False)
    keep = int(min(3, (sv > 1e-6 * max(sv.max(), 1e-12)).sum()))
    if keep == 0:
        return None
    design = np.column_stack([u[:, :keep] * sv[:keep], np.ones(n)])

    def fit(shift: int) -> tuple[np.ndarray, float]:
        d = np.roll(design, shift, axis=0)
        use = ok.copy()
        use[: max(shift, 0)] = use[n + min(shift, 0) :] = False
        coef, *_ = np.linalg.lstsq(d[use], m[use], rcond=None)
        r2 = 1 - np.var(m[use] - d[use] @ coef) / max(np.var(m[use]), 1e-18)
        return design @ coef, float(r2)

    return m, fit


def picture_lag(
    track_values: np.ndarray, mouth: np.ndarray, *, max_lag: int = 8
) -> tuple[float, float]:
    """(lag, R²): how many frames the tracked mouth opening follows the animation track. The
    track's channels (n, K) are reduced to their first three principal components, fitted to
    the opening by least squares (R² of that fit), and the fitted opening is cross-correlated
    with the tracked one (:func:`sync_lag`). NaN without enough tracked frames."""
    found = _track_fit(track_values, mouth)
    if found is None:
        return math.nan, math.nan
    m, fit = found
    fitted, _ = fit(0)
    lag, _ = sync_lag(fitted, m, max_lag=max_lag)
    if math.isnan(lag):
        return math.nan, math.nan
    _, r2 = fit(round(lag))
    return lag, r2


def lag_is_identifiable(
    track_values: np.ndarray, mouth: np.ndarray, *, lag: float, max_lag: int = 8
) -> bool:
    """False when the track fits the tracked opening at least as well at a shift two or more
    frames from ``lag`` (R² of the same fit): e.g. a short word whose one mouth opening any of
    several viseme channels can be slid onto - the picture's timing cannot be read there."""
    found = _track_fit(track_values, mouth)
    if found is None or math.isnan(lag):
        return False
    _, fit = found
    at = round(lag)
    chosen = fit(at)[1]
    return all(fit(k)[1] < chosen for k in range(-max_lag, max_lag + 1) if abs(k - at) >= 2)


#: the tracked mouth must follow the animation track this closely (R² of the fit) for its lag
#: to be trusted; below it the offset is a warning
MIN_FIT_R2 = 0.5
#: ITU-R BT.1359: sound before the picture becomes detectable at 45 ms, after it at 125 ms
SOUND_LEADS_MS, SOUND_LAGS_MS = 45.0, 125.0


def av_sync_rows(
    tr: ClipTracking, sound: np.ndarray, *, track_values: np.ndarray, intended_sound: np.ndarray,
    fps: float, clip: str, condition: str, intended_offset_ms: float = 0.0,
    sound_lag_frames: float | None = None,
) -> list[CheckRow]:  # fmt: skip
    """Audio-visual sync of one clip, measured on what it delivers:

    * ``av_offset_frames`` (error beyond ±:data:`MAX_LAG_FRAMES`): how many frames later the
      picture is than the sound, against what the animation intends - the picture's lag behind
      the animation track (:func:`picture_lag`: tracked mouth opening vs the track's channels)
      less the sound's lag behind the intended audio (decoded envelope ``sound`` vs
      ``intended_sound``, the stimulus' own audio). A clip muxed or drawn out of step fails.
      With ``intended_offset_ms`` (a synchrony task's offset: positive, the voice follows) the
      sound must lag by that much: the row measures the departure from it.
    * ``mouth_lag_ms``: the tracked mouth opening's lag behind the sound's level by
      cross-correlation (positive: the mouth follows), a warning outside ITU-R BT.1359's
      detectability window (sound at most 45 ms before, 125 ms after the picture); with an
      intended offset, the lag beyond the one intended.

    A voice in noise (``sound_lag_frames`` given: the mix found in the decoded sound, see
    :func:`mix_lag`) is timed by that lag instead of the sound's level, which the noise
    blurs; the mouth-against-level row is then left out.
    """
    kw = {"clip": clip, "condition": condition, "check": "av_sync"}
    frame_ms = 1000.0 / fps
    shift = intended_offset_ms / frame_ms  # frames the sound is meant to follow
    reach = MAX_SEARCH_FRAMES + math.ceil(abs(shift))
    lag, corr = sync_lag(sound, tr.aperture, max_lag=reach)
    lag = lag + shift if not math.isnan(lag) else lag
    picture, fit = picture_lag(track_values, tr.aperture)
    if sound_lag_frames is None:
        audio, audio_corr = sync_lag(intended_sound, sound, max_lag=reach)
        audio = audio - shift if not math.isnan(audio) else audio
    else:  # the mix's own place (the noise is part of what was put there)
        audio, audio_corr = sound_lag_frames, 1.0
    offset = picture - audio if not (math.isnan(picture) or math.isnan(audio)) else None
    unique = offset is not None and lag_is_identifiable(track_values, tr.aperture, lag=picture)
    loose = offset is not None and (fit < MIN_FIT_R2 or not unique)
    rows = [
        at_most(MAX_LAG_FRAMES, abs(offset) if offset is not None else None,
                measure="av_offset_frames",
                note=(f"picture {picture:+.2f} frames behind its animation track (fit R² "
                      f"{fit:.2f}), sound {audio:+.2f} frames behind the stimulus audio "
                      + (f"shifted {intended_offset_ms:+g} ms as intended " if shift else "")
                      + f"(correlation {audio_corr:.2f})"
                      + ("; the tracked mouth follows the track too loosely to time it"
                         if fit < MIN_FIT_R2 else "")
                      + ("; the track fits the tracked mouth as well at another lag two or "
                         "more frames away: the picture's timing cannot be read on this clip"
                         if not unique else "")) if offset is not None
                else "too few frames with a tracked mouth",
                severity="warning" if loose or offset is None else "error", **kw),
        info(offset, measure="av_offset_signed_frames", note="positive: the picture is late", **kw),
    ]  # fmt: skip
    if sound_lag_frames is not None:
        return rows
    lag_ms = lag * frame_ms if not math.isnan(lag) else math.nan
    inside = not math.isnan(lag_ms) and -SOUND_LAGS_MS <= lag_ms <= SOUND_LEADS_MS
    rows.append(CheckRow(
        **kw, measure="mouth_lag_ms", value=lag_ms,
        threshold=f">= -{SOUND_LAGS_MS:g} and <= {SOUND_LEADS_MS:g} ms", passed=inside,
        note=f"tracked mouth opening vs the sound's level, correlation {corr:.2f} (positive: "
        "the mouth follows the sound; ITU-R BT.1359 detectability)"
        + (f"; beyond the intended offset of {intended_offset_ms:+g} ms" if shift else ""),
        severity="warning",
    ))  # fmt: skip
    return rows


#: a clip's measured SNR and speech level may differ from those asked by this much (dB)
NOISE_TOLERANCE_DB = 1.0


def mix_lag(sound: np.ndarray, intended: np.ndarray, *, sample_rate: int) -> int:
    """Samples by which ``intended`` (a clip's sound as made) follows in the decoded ``sound``
    (negative: it comes early), the peak of their cross-correlation within ±100 ms."""
    n = min(len(sound), len(intended))
    d, m = np.asarray(sound[:n], np.float64), np.asarray(intended[:n], np.float64)
    if n < 2:
        return 0
    reach = min(round(0.1 * sample_rate), n - 1)
    # zero-padded to at least 2n (no wrap-around) and to a length of small prime factors: a
    # clip's sample count is often near-prime, where the FFT is up to 10x slower
    size = sfft.next_fast_len(2 * n, real=True)
    corr = sfft.irfft(sfft.rfft(d, size) * np.conj(sfft.rfft(m, size)), size)
    lags = np.r_[np.arange(0, reach + 1), np.arange(-reach, 0)]  # circular: negative at the end
    return int(lags[np.argmax(corr[lags % size])])


def noise_rows(
    sound: np.ndarray, intended: np.ndarray, *, quiet: np.ndarray, sample_rate: int,
    snr_db: float, noise_dbfs: float, fps: float, clip: str, condition: str,
    lag: int | None = None,
) -> list[CheckRow]:  # fmt: skip
    """A speech-in-noise clip's sound, measured (``check`` noise). ``intended`` is the mix
    as made (:func:`facelab.stimuli.render.sound.clip_sound`), ``quiet`` marks its samples
    where the voice is silent and the noise steady (between its fades); ``lag``: the
    :func:`mix_lag` of the two when it was measured already.

    * ``speech_lag_ms``: the intended mix found in the decoded sound by cross-correlation, at
      most one frame from where it was put;
    * ``mix_error_db``: what the decoded sound holds besides the intended mix, relative to it
      (at most -20 dB: the file carries this mix, at its level - not another SNR's);
    * ``noise_level_error``: the noise's RMS where the voice is silent, measured on the
      decoded sound, within :data:`NOISE_TOLERANCE_DB` of the mix made in the same samples
      (a noise file's level wanders: the clip's padding need not hold the level set over the
      clip; the speech level itself cannot be read blind under noise: its share of a mix at
      -18 dB SNR moves the least-squares estimate by several dB).
    """
    from facelab.stimuli.speech.noise import rms_db

    kw = {"clip": clip, "condition": condition, "check": "noise"}
    n = min(len(sound), len(intended), len(quiet))
    d, m = np.asarray(sound[:n], np.float64), np.asarray(intended[:n], np.float64)
    if n == 0 or not np.any(m):
        return [at_most(-20.0, None, measure="mix_error_db", note="no sound to measure", **kw)]
    lag = mix_lag(d, m, sample_rate=sample_rate) if lag is None else lag
    m = np.roll(m, lag)
    error = rms_db(d - m) - rms_db(m)
    steady = np.asarray(quiet[:n], bool)
    enough = steady.sum() >= 0.05 * sample_rate
    noise = rms_db(d[steady]) if enough else None
    noise_dbfs = rms_db(m[steady]) if enough else noise_dbfs  # the mix made, same samples
    return [
        at_most(1000.0 / fps, abs(1000.0 * lag / sample_rate), measure="speech_lag_ms",
                note="the mix's place in the clip against where it was put", unit="ms", **kw),
        at_most(-20.0, error, measure="mix_error_db",
                note=f"the decoded sound against the mix made for {snr_db:+g} dB SNR",
                unit="dB", **kw),
        at_most(NOISE_TOLERANCE_DB, abs(noise - noise_dbfs) if noise is not None else None,
                measure="noise_level_error",
                note=(f"noise at {noise:.2f} dBFS where the voice is silent, asked "
                      f"{noise_dbfs:.2f}" if noise is not None
                      else "too little of the clip without the voice to measure the noise"),
                unit="dB", **kw),
    ]  # fmt: skip


def face_difference(a: ClipTracking, b: ClipTracking, *, blocks: int = 8) -> float:
    """How much two clips differ on the face, in grey levels (0-255): the face region (the two
    clips' median face boxes joined) is cut into ``blocks`` x ``blocks`` tiles, each frame
    scores the largest mean |grey difference| of any tile (a change at the mouth is not
    averaged away by the forehead), and the clip pair scores the 95th percentile over frames.
    0 for identical pictures."""
    boxes = np.vstack([a.box, b.box])
    boxes = boxes[~np.isnan(boxes).any(axis=1)]
    n = min(len(a.grey), len(b.grey))
    if n == 0:
        return math.nan
    h, w = a.grey.shape[1:]
    if len(boxes):
        x0, y0 = np.median(boxes[:, :2], axis=0)
        x1, y1 = np.median(boxes[:, 2:], axis=0)
        c0, c1 = max(0, int(x0 * w)), min(w, math.ceil(x1 * w))
        r0, r1 = max(0, int(y0 * h)), min(h, math.ceil(y1 * h))
    else:
        r0, r1, c0, c1 = 0, h, 0, w
    bh, bw = max(1, (r1 - r0) // blocks), max(1, (c1 - c0) // blocks)
    kr, kc = (r1 - r0) // bh, (c1 - c0) // bw
    ga = a.grey[:n, r0 : r0 + kr * bh, c0 : c0 + kc * bw].astype(np.int16)
    gb = b.grey[:n, r0 : r0 + kr * bh, c0 : c0 + kc * bw].astype(np.int16)
    tiles = np.abs(ga - gb).reshape(n, kr, bh, kc, bw).mean(axis=(2, 4))
    return float(np.percentile(tiles.reshape(n, -1).max(axis=1), 95))


def difference_rows(
    clips: Mapping[str, tuple[str, ClipTracking, str]],
    *,
    equal_groups: Sequence[Sequence[str]] = (),
    shared_picture: Sequence[Sequence[str]] = (),
    explain: Mapping[tuple[str, str], str] | None = None,
) -> list[CheckRow]:
    """``clips`` {condition: (clip id, tracking, sha256)} of one stimulus: every pair of
    conditions differs over the face (:data:`FACE_DIFFERENCE`), unless a group of
    ``equal_groups`` (declared) or ``shared_picture`` (one picture for several audio offsets)
    holds both - then they must not. ``explain`` {(a, b): why} is added to a failure's note."""
    rows = []
    explain = explain or {}
    for ca, cb in itertools.combinations(sorted(clips), 2):
        ida, ta, sha = clips[ca]
        idb, tb, shb = clips[cb]
        value = 0.0 if sha == shb else face_difference(ta, tb)
        declared = any(ca in g and cb in g for g in equal_groups)
        shared = any(ca in g and cb in g for g in shared_picture)
        same = declared or shared
        measure = f"face_difference_p95:{ca}~{cb}"
        kw = {"clip": f"{ida}~{idb}", "condition": f"{ca}~{cb}", "check": "conditions_differ",
              "measure": measure}  # fmt: skip
        byte_note = "byte-identical clips" if sha == shb else ""
        if same:
            why = ("declared equal (checks.equal_conditions)" if declared else
                   "one picture, the voice at another offset (audio_offset_ms)")  # fmt: skip
            row = at_most(FACE_DIFFERENCE, value, note=why, **kw)
        else:
            row = at_least(FACE_DIFFERENCE, value, **kw)
            if not row.passed:
                why = explain.get((ca, cb)) or explain.get((cb, ca)) or ""
                row = CheckRow(**{**row.__dict__, "note": "; ".join(
                    x for x in (byte_note, "the conditions render alike on the face", why) if x
                ) + " (declare them in checks.equal_conditions if that is meant)"})  # fmt: skip
        rows.append(row)
    return rows


def level_rows(
    levels: Sequence[tuple[float, str, ClipTracking]], *, condition_of: Mapping[str, str],
    group: str,
) -> list[CheckRow]:  # fmt: skip
    """Graded stimuli of one dimension ``levels`` [(level, clip id, tracking)]: each step
    between neighbouring levels changes the face by :data:`FACE_DIFFERENCE` or more, and the
    change from the lowest level grows with the level (monotone)."""
    ordered = sorted(levels, key=lambda x: x[0])
    rows: list[CheckRow] = []
    if len(ordered) < 2:
        return rows
    lowest = ordered[0][2]
    from_lowest = [0.0]
    for (qa, ida, ta), (qb, idb, tb) in itertools.pairwise(ordered):
        step = face_difference(ta, tb)
        rows.append(at_least(FACE_DIFFERENCE, step, clip=idb, condition=condition_of.get(idb, ""),
                             check="levels", measure=f"step_difference:{group} {qa:g}->{qb:g}",
                             note=f"{ida} to {idb}"))  # fmt: skip
        from_lowest.append(face_difference(lowest, tb))
    rises = all(b >= a for a, b in itertools.pairwise(from_lowest))
    rows.append(CheckRow(ordered[-1][1], "", "levels", f"monotone:{group}", float(rises), "= 1",
                         rises, "change from the lowest level per level: " +
                         ", ".join(f"{q:g}: {d:.2f}" for (q, _, _), d in
                                   zip(ordered, from_lowest, strict=True))))  # fmt: skip
    return rows
