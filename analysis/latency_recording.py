"""A photodiode and microphone recording of a latency test clip, measured: how much later the
sound arrived than the light, event by event.

The recording holds the photodiode's signal on one channel and the microphone's on another
(one sound card, one clock). The light is high-passed at 10 Hz as a line input's DC block
would (a DC-coupled input's resting level does not matter), the microphone band-passed
around the tone (mains hum and its harmonics removed); then each channel is measured the
same way: its deviation from its median (either polarity), a trailing maximum as its
envelope (2 ms for the tone's cycles, 10 ms for a backlight's PWM flicker; nothing is
anticipated, so the onset is not moved by it), candidate events where the envelope rises
through half of its high percentile, one per half period (of several rises, the one with
the most energy over the next 10 ms: a click before a burst is passed over); each event's
onset is where the envelope first rose through ``onset_fraction`` of its typical peak
above the floor (at least 8 noise deviations above it), interpolated between samples. Each
light is paired with the sound onset nearest to it within half a period (a sound later
than that is paired with the wrong flash: the summary warns when flashes go unpaired).

``offset_ms`` = sound onset - light onset: positive when the sound comes late. The lights'
intervals against the schedule's period show frames shown late or dropped (a flash that came
a frame late shifts one interval up and the next down by a frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pandas as pd

from facelab.errors import StageError

__all__ = ["LatencyMeasure", "channel_onsets", "measure_latency"]

#: the trailing maximum's length per channel: the tone's cycles (1 kHz) are filled in within
#: 2 ms; a backlight's PWM flicker (down to 100 Hz) riding on the light within 10 ms
MIC_ENVELOPE_S = 0.002
LIGHT_ENVELOPE_S = 0.010
#: the photodiode channel is high-passed (causal, 1st order) as a line input's DC block
#: would: a DC-coupled input's resting level (a grey screen before the clip) does not matter,
#: the flash's leading edge is kept
LIGHT_HIGHPASS_HZ = 10.0
SEARCH_S = 0.05  # how far before a strong crossing its onset is looked for
HOLD_S = 0.01  # of the rises within half a period, the one with the most energy after it


def _envelope(x: np.ndarray, *, sample_rate: int, window_s: float) -> np.ndarray:
    a = np.abs(x.astype(np.float64) - float(np.median(x)))
    w = max(1, round(window_s * sample_rate))
    padded = np.concatenate([np.zeros(w - 1), a])
    return np.lib.stride_tricks.sliding_window_view(padded, w).max(axis=1)


def channel_onsets(
    x: np.ndarray,
    *,
    sample_rate: int,
    min_gap_s: float,
    onset_fraction: float = 0.1,
    envelope_s: float = MIC_ENVELOPE_S,
    highpass_hz: float | None = None,
    band_hz: tuple[float, float] | None = None,
    brightening: bool = False,
) -> np.ndarray:
    """Event onsets (s) in one channel ``x`` (n,): see the module's description. Empty when
    the channel holds no events standing out of its noise. ``highpass_hz``: a causal 1st
    order high-pass first; ``band_hz``: a causal 2nd-order band-pass (the tone's band);
    ``brightening``: only changes of the flashes' direction count (the direction most events
    start with: a flash's end, or a grey screen turning to the clip's dark, is not one)."""
    from scipy.signal import butter, lfilter

    x = x.astype(np.float64)
    if highpass_hz is not None:
        b, a = butter(1, highpass_hz / (sample_rate / 2), "high")
        x = lfilter(b, a, x - x[0])
    if band_hz is not None:
        nyquist = sample_rate / 2
        b, a = butter(2, [band_hz[0] / nyquist, min(band_hz[1] / nyquist, 0.95)], "band")
        x = lfilter(b, a, x)
    if brightening:
        x = x - float(np.median(x))
        firsts = _clusters(_envelope(x, sample_rate=sample_rate, window_s=envelope_s),
                           sample_rate=sample_rate, min_gap_s=min_gap_s, first=True)  # fmt: skip
        if not firsts:
            return np.empty(0)
        way = 1.0 if sum(np.sign(x[k]) for k in firsts) >= 0 else -1.0
        x = np.maximum(way * x, 0.0)
    return _onsets(x, sample_rate=sample_rate, min_gap_s=min_gap_s,
                   onset_fraction=onset_fraction, envelope_s=envelope_s)  # fmt: skip


def _clusters(env: np.ndarray, *, sample_rate: int, min_gap_s: float, first: bool) -> list[int]:
    """The strong rises of the envelope ``env``, one per half period: each cluster's first
    (``first``) or the one with the most energy after it."""
    floor = float(np.median(env))
    spread = 1.4826 * float(np.median(np.abs(env - floor)))
    top = float(np.percentile(env, 99.9))
    if top - floor <= 20 * max(spread, 1e-9):
        return []  # nothing stands out of the noise
    above = env >= floor + 0.5 * (top - floor)
    rises = np.flatnonzero(above[1:] & ~above[:-1]) + 1
    gap = round(min_gap_s * sample_rate)
    hold = max(1, round(HOLD_S * sample_rate))
    clusters: list[list[int]] = []  # rises within half a period of a cluster's first
    for k in rises:
        if not clusters or k - clusters[-1][0] >= gap:
            clusters.append([int(k)])
        else:
            clusters[-1].append(int(k))
    if first:
        return [c[0] for c in clusters]
    # a click before a burst rises too: the rise with the most energy after it is the event
    return [max(c, key=lambda k: float(env[k : k + hold].mean())) for c in clusters]


def _onsets(
    x: np.ndarray, *, sample_rate: int, min_gap_s: float, onset_fraction: float,
    envelope_s: float,
) -> np.ndarray:
    env = _envelope(x, sample_rate=sample_rate, window_s=envelope_s)  # once, for both steps
    strong = _clusters(env, sample_rate=sample_rate, min_gap_s=min_gap_s, first=False)
    if not strong:
        return np.empty(0)
    floor = float(np.median(env))
    spread = 1.4826 * float(np.median(np.abs(env - floor)))
    search = round(SEARCH_S * sample_rate)
    peaks = np.array([env[k : k + search].max() for k in strong])
    typical = float(np.median(peaks))
    low = floor + max(onset_fraction * (typical - floor), 8 * spread)
    onsets = []
    for k in strong:
        start = max(0, k - search)
        below = np.flatnonzero(env[start:k] < low)
        if not below.size:  # never under the threshold just before: no onset to read
            continue
        j = start + int(below[-1])  # the last sample under the threshold
        # between sample j (under) and j + 1 (at or over), linearly
        a, b = env[j], env[min(j + 1, len(env) - 1)]
        frac = 0.0 if b <= a else float(np.clip((low - a) / (b - a), 0.0, 1.0))
        onsets.append((j + frac) / sample_rate)
    return np.array(onsets)


@dataclass(frozen=True)
class LatencyMeasure:
    """Per event (``events``: event, light_s, sound_s, offset_ms, light_interval_ms) and the
    summary figures (``summary``: counts, offset mean, SD, median, range, the lights'
    largest interval error against the schedule)."""

    events: pd.DataFrame
    summary: dict


def measure_latency(
    recording: np.ndarray,
    *,
    sample_rate: int,
    photodiode: int,
    mic: int,
    period_s: float,
    tone_hz: float = 1000.0,
    expected: int | None = None,
    source: str = "the recording",
) -> LatencyMeasure:
    """Measure a (n, channels) ``recording`` of a latency test clip; ``period_s`` the
    schedule's period, ``expected`` its event count. A StageError when a channel is missing
    or holds fewer than three events."""
    if recording.ndim != 2:
        raise StageError(f"{source}: expected a recording of shape (samples, channels)")
    channels = recording.shape[1]
    for name, k in (("photodiode", photodiode), ("microphone", mic)):
        if not 0 <= k < channels:
            raise StageError(
                f"{source} has {channels} channel{'s' * (channels != 1)} (0 to {channels - 1});"
                f" the {name} channel {k} is not one of them"
            )
    if photodiode == mic:
        raise StageError(f"the photodiode and the microphone are both channel {mic}: record "
                         "them on two channels of one recording")  # fmt: skip
    gap = period_s / 2
    light = channel_onsets(recording[:, photodiode], sample_rate=sample_rate, min_gap_s=gap,
                           envelope_s=LIGHT_ENVELOPE_S, highpass_hz=LIGHT_HIGHPASS_HZ,
                           brightening=True)  # fmt: skip
    sound = channel_onsets(recording[:, mic], sample_rate=sample_rate, min_gap_s=gap,
                           band_hz=(tone_hz / 2, tone_hz * 2))  # fmt: skip
    for name, k, found, hint in (
        ("flashes", photodiode, light, "is the photodiode on the white patch, its cable in "
         "the line input, and the clip playing?"),
        ("tone bursts", mic, sound, "is the microphone near the participant's head, the "
         "sound on, and no hum louder than the tone?"),
    ):  # fmt: skip
        if len(found) < 3:
            raise StageError(
                f"{source}: {len(found)} {name} found on channel {k} (at least 3 are needed): "
                f"{hint}"
            )
    rows = []
    used: set[int] = set()
    for i, t in enumerate(light):
        j = int(np.argmin(np.abs(sound - t)))
        paired = abs(sound[j] - t) <= gap and j not in used
        if paired:
            used.add(j)
        rows.append({
            "event": i + 1,
            "light_s": round(float(t), 6),
            "sound_s": round(float(sound[j]), 6) if paired else np.nan,
            "offset_ms": round(1000 * float(sound[j] - t), 3) if paired else np.nan,
            "light_interval_ms": round(1000 * float(t - light[i - 1]), 3) if i else np.nan,
        })  # fmt: skip
    events = pd.DataFrame(rows)
    offsets = events["offset_ms"].dropna().to_numpy()
    if len(offsets) < 3:
        raise StageError(f"{source}: only {len(offsets)} flashes have a tone burst within half "
                         "a period: is this a recording of the latency test clip?")  # fmt: skip
    intervals = events["light_interval_ms"].dropna().to_numpy()
    steps = np.round(intervals / (1000 * period_s))  # a missing flash: two periods
    error = intervals - 1000 * period_s * np.maximum(steps, 1)
    summary = {
        "events_expected": expected,
        "flashes_found": len(light),
        "tone_bursts_found": len(sound),
        "pairs": len(offsets),
        "offset_ms_mean": round(float(offsets.mean()), 3),
        "offset_ms_sd": round(float(offsets.std(ddof=1)), 3),
        "offset_ms_median": round(float(np.median(offsets)), 3),
        "offset_ms_min": round(float(offsets.min()), 3),
        "offset_ms_max": round(float(offsets.max()), 3),
        "light_interval_error_ms_max": round(float(np.abs(error).max()), 3) if len(error) else None,
        "flashes_missing": (max(0, expected - len(light)) if expected is not None else None),
    }
    warnings = []
    if expected is not None and len(offsets) > expected:
        warnings.append(f"{len(offsets)} flashes with tone bursts for a clip of {expected}: "
                        "record one playing per measurement")  # fmt: skip
    unpaired = int(events["offset_ms"].isna().sum())
    if unpaired > 1 or abs(summary["offset_ms_mean"]) > 250 * period_s:  # one: a screen change
        warnings.append(
            f"{unpaired} flashes without a tone burst within half a period, mean offset "
            f"{summary['offset_ms_mean']:.0f} ms: if the sound is more than "
            f"{500 * period_s:.0f} ms late (a wireless speaker) it is paired with the wrong "
            "flash; write a clip with a longer --period-ms"
        )
    summary["warnings"] = warnings
    return LatencyMeasure(events, summary)
