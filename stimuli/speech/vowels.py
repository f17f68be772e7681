"""Vowels of a track: per-vowel segments, calibration on a speaker's five vowels, and
isolation of the intended vowel (seed figure 7).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import replace

import numpy as np

from facelab.errors import VisemeError
from facelab.stimuli.speech.analyser import VisemeModel, analyze, features
from facelab.stimuli.speech.audio import Phone
from facelab.stimuli.speech.features import HOP_S
from facelab.stimuli.speech.track import VISEMES, VOWEL_INDEX, VOWEL_VISEMES, VOWELS, VisemeTrack
from facelab.stimuli.speech.vowel_units import Unit, vowel_readings

__all__ = [
    "calibrate",
    "isolate_vowels",
    "phone_vowel_segments",
    "vowel_segments",
    "vowel_stretches",
]

# --------------------------------------------------------------------------- calibration


def vowel_segments(
    track: VisemeTrack,
    *,
    min_s: float = 0.06,
    merge_gap_s: float = 0.08,
    threshold: float = 0.5,
    widen: bool = False,
) -> list[tuple[int, int]]:
    """Voiced stretches as frame index ranges [start, stop): where 1 - sil >= threshold,
    gaps shorter than ``merge_gap_s`` merged, pieces shorter than ``min_s`` dropped; with
    ``widen``, each grown over its rising and falling edges (as vowel isolation uses them)."""
    active = (1.0 - track.weights[:, 0]) >= threshold
    fps = track.fps
    segs: list[list[int]] = []
    for i, on in enumerate(active):
        if not on:
            continue
        if segs and i - segs[-1][1] <= merge_gap_s * fps:
            segs[-1][1] = i + 1
        else:
            segs.append([i, i + 1])
    kept = [(a, b) for a, b in segs if (b - a) >= min_s * fps]
    return _widen(track, kept) if widen else kept


def calibrate(
    model: VisemeModel,
    samples: np.ndarray,
    *,
    sample_rate: int,
    vowels: str = "aiueo",
    prior_frames: float = 20.0,
    steps: int = 60,
) -> VisemeModel:
    """Adapt ``model`` to a speaker from a recording of the vowels spoken in ``vowels`` order
    with pauses between them (e.g. あ、い、う、え、お).

    Vowel segments are found with the model's own voicing decision, their middle 60 % frames
    are used:

    1. an input bias (feature units) moves the speaker's vowels onto the training vowels: the
       mean over vowels of (segment mean - class mean), each shrunk by n / (n + prior_frames);
    2. the output layer is then fitted to those frames by ``steps`` of gradient descent on the
       cross-entropy plus a penalty pulling it back to the shipped weights (strength
       ``prior_frames`` frames' worth), so a handful of frames moves it only as far as they
       justify;
    3. the level gate is set from the vowel level (peak 2 dB below its 90th percentile).

    The calibrated model runs at warp 1 (the calibration replaces the warp search).
    """
    track = analyze(samples, sample_rate=sample_rate, model=model, warp=1.0)
    segs = vowel_segments(track)
    if len(segs) != len(vowels):
        raise VisemeError(
            f"calibration recording: found {len(segs)} voiced segments, expected "
            f"{len(vowels)} ({vowels}); leave clear pauses between the vowels"
        )
    _, x = features(samples, sample_rate=sample_rate, normalisation=model.normalisation)
    cores, labels, shifts = [], [], []
    for (a, b), vowel in zip(segs, vowels, strict=True):
        n = b - a
        core = x[a + int(0.2 * n) : b - int(0.2 * n), 1:]
        c = model.classes.index(VOWEL_VISEMES[VOWELS.index(vowel)])
        shifts.append(
            (core.mean(axis=0) - model.class_means[c]) * len(core) / (len(core) + prior_frames)
        )
        cores.append(core)
        labels += [c] * len(core)
    tuned = replace(model, input_bias=np.mean(shifts, axis=0))
    feats, target = np.vstack(cores), np.array(labels)
    z = (feats - tuned.input_bias - tuned.scale_mean) / tuned.scale_sd
    hidden = np.maximum(z @ tuned.hidden_w + tuned.hidden_b, 0.0)
    w0, b0 = tuned.out_w, tuned.out_b
    w, b = w0.copy(), b0.copy()
    onehot = np.eye(len(model.classes))[target]
    strength = prior_frames / len(feats)
    rate = 0.5 / max(float(np.mean(np.sum(hidden**2, axis=1))), 1e-9)
    for _ in range(steps):
        logits = hidden @ w + b
        logits -= logits.max(axis=1, keepdims=True)
        p = np.exp(logits)
        p /= p.sum(axis=1, keepdims=True)
        grad = (p - onehot) / len(feats)
        w -= rate * (hidden.T @ grad + strength * (w - w0))
        b -= rate * (grad.sum(axis=0) + strength * (b - b0))
    levels = np.concatenate([x[a:b_, 0] for a, b_ in segs])
    top = float(np.percentile(levels, 90)) - 2.0
    info = {
        **model.info,
        "calibrated": {"vowels": vowels, "segments_s": [[a * HOP_S, e * HOP_S] for a, e in segs]},
    }
    return replace(tuned, out_w=w, out_b=b, gate_db=(top - 20.0, top), info=info)


# --------------------------------------------------------------------------- vowel isolation


def _widen(
    track: VisemeTrack, segs: list[tuple[int, int]], *, floor: float = 0.02
) -> list[tuple[int, int]]:
    """Grow each segment over its rising and falling edges (while 1 - sil > ``floor``),
    never into a neighbour."""
    active = (1.0 - track.weights[:, 0]) > floor
    out: list[tuple[int, int]] = []
    for i, (a, b) in enumerate(segs):
        lo = out[-1][1] if out else 0
        hi = segs[i + 1][0] if i + 1 < len(segs) else len(active)
        while a > lo and active[a - 1]:
            a -= 1
        while b < hi and active[b]:
            b += 1
        out.append((a, b))
    return out


def phone_vowel_segments(
    units: Sequence[Unit], phones: Sequence[Phone], track: VisemeTrack
) -> list[tuple[int, int]]:
    """One frame range [start, stop) of ``track`` per vowel unit (:func:`vowel_readings`):
    the unit's own time grown half-way to the units either side, or to the pause or silence
    between them. Vowels run together (あいうえお, はい) get one each, where
    :func:`vowel_segments` finds one voiced stretch for all of them."""
    times = np.asarray(track.times, float)
    pauses = [(p.start, p.end) for p in phones if p.phoneme in ("pau", "sil")]

    def pause_between(t0: float, t1: float) -> list[tuple[float, float]]:
        return [(a, b) for a, b in pauses if a >= t0 - 1e-9 and b <= t1 + 1e-9]

    out: list[tuple[int, int]] = []
    for n, (_, start, end) in enumerate(units):
        lo, hi = start, end
        if n > 0:  # half-way back to the unit before, or to the pause after it
            gap = pause_between(units[n - 1][2], start)
            lo = gap[-1][1] if gap else (units[n - 1][2] + start) / 2
        if n + 1 < len(units):
            gap = pause_between(end, units[n + 1][1])
            hi = gap[0][0] if gap else (end + units[n + 1][1]) / 2
        a = min(int(np.searchsorted(times, lo)), len(times) - 1)
        b = min(max(int(np.searchsorted(times, hi)), a + 1), len(times))
        out.append((a, b))
    return out


def vowel_stretches(
    track: VisemeTrack, *, vowels: str, phones: Sequence[Phone] = ()
) -> list[tuple[int, int]]:
    """One frame range of ``track`` per vowel of ``vowels`` (a stimulus' ``expected_vowels``):
    its voiced stretches, widened (vowels spoken apart, as the seed's あ。い。う。え。お。),
    or, when those are not one per vowel and the words are known (``phones``), the units of
    the reading of the words that ``vowels`` is (:func:`vowel_readings`,
    :func:`phone_vowel_segments`). VisemeError when neither fits."""
    segs = vowel_segments(track, widen=True)
    if phones:
        readings = vowel_readings(phones)
        if vowels not in readings:
            raise VisemeError(
                f"expected_vowels is {vowels!r}, but the words' vowels are "
                + " or ".join(repr(r) for r in readings) + ": give one of those"
            )
        if len(segs) != len(vowels):  # run together: one stretch per vowel from the words
            return phone_vowel_segments(readings[vowels], phones, track)
    if len(segs) == len(vowels):  # spoken apart: the voiced stretches, as always
        return segs
    raise VisemeError(
        f"expected_vowels is {vowels!r} ({len(vowels)} vowels), but the recording has "
        f"{len(segs)} voiced stretch(es): without its words, a recording's vowels are told "
        "apart by the pauses between them - give it its 'transcript', or record the vowels "
        "apart"
    )


def isolate_vowels(
    track: VisemeTrack, *, vowels: str, segments: Iterable[tuple[int, int]] | None = None
) -> VisemeTrack:
    """Keep only the intended vowel per vowel segment (seed figure 7).

    In the i-th voiced segment the vowel ``vowels[i]`` keeps its intensity and the other four
    vowel columns are set to 0; consonant columns are left alone; ``sil`` takes the rest.
    Segments are found from the track (:func:`vowel_segments`, widened) unless given.
    """
    segs = list(segments) if segments is not None else vowel_segments(track, widen=True)
    if len(segs) != len(vowels):
        raise VisemeError(
            f"vowel isolation: found {len(segs)} voiced segments but expected_vowels "
            f"is {vowels!r} ({len(vowels)}); check the recording or the text"
        )
    weights = track.weights.copy()
    for (a, b), vowel in zip(segs, vowels, strict=True):
        keep = VISEMES.index(VOWEL_VISEMES[VOWELS.index(vowel)])
        for col in VOWEL_INDEX:
            if col != keep:
                weights[a:b, col] = 0.0
    weights[:, 0] = 0.0
    weights[:, 0] = np.clip(1.0 - weights.sum(axis=1), 0.0, 1.0)
    return replace(track, weights=weights)
