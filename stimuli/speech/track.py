"""The viseme track type and the text-driven track.

Output order is Oculus LipSync's: ``sil PP FF TH DD kk CH SS nn RR aa E ih oh ou``; the five
Japanese vowels a, i, u, e, o are ``aa, ih, ou, E, oh``. :func:`from_phonemes` makes a track
from a phoneme timeline (TTS or alignment), with coarticulation smoothing.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from facelab.errors import VisemeError
from facelab.stimuli.arkit import OCULUS_VISEMES

__all__ = [
    "FPS",
    "VISEMES",
    "VOWELS",
    "VOWEL_VISEMES",
    "VisemeTrack",
    "from_phonemes",
    "phoneme_viseme",
]

VISEMES: tuple[str, ...] = OCULUS_VISEMES
VOWELS: tuple[str, ...] = ("a", "i", "u", "e", "o")
VOWEL_VISEMES: tuple[str, ...] = ("aa", "ih", "ou", "E", "oh")
VOWEL_INDEX = [VISEMES.index(v) for v in VOWEL_VISEMES]
FPS = 100.0



# --------------------------------------------------------------------------- the track


@dataclass(frozen=True)
class VisemeTrack:
    """Viseme weights over time.

    times : (T,) seconds, frame times (uniform, ``fps`` per second).
    weights : (T, 15) in [0, 1], columns in :data:`VISEMES` order, rows summing to 1.
    latency_s : how late the weights are relative to the audio at the frame times (the
        analyser's smoothing lag; 0 for text-driven tracks). ``compensated()`` removes it.
    """

    times: np.ndarray
    weights: np.ndarray
    names: tuple[str, ...] = VISEMES
    latency_s: float = 0.0
    warp: float = 1.0  # the mel-filter warp the analyser used (vocal-tract normalisation)

    @property
    def fps(self) -> float:
        return (
            FPS if len(self.times) < 2 else float(round(1.0 / (self.times[1] - self.times[0]), 6))
        )

    def vowels(self) -> np.ndarray:
        """(T, 5) intensities of a, i, u, e, o (the aa, ih, ou, E, oh columns)."""
        return self.weights[:, VOWEL_INDEX]

    def compensated(self) -> VisemeTrack:
        """The track moved earlier by its latency (linear interpolation on the same times)."""
        if self.latency_s == 0:
            return self
        shifted = np.empty_like(self.weights)
        for j in range(self.weights.shape[1]):
            shifted[:, j] = np.interp(self.times + self.latency_s, self.times, self.weights[:, j])
        return replace(self, weights=shifted, latency_s=0.0)


# --------------------------------------------------------------------------- phonemes -> visemes

_CONSONANT_VISEME = {
    "p": "PP",
    "b": "PP",
    "m": "PP",
    "py": "PP",
    "by": "PP",
    "my": "PP",
    "f": "FF",
    "v": "FF",
    "t": "DD",
    "d": "DD",
    "ty": "DD",
    "dy": "DD",
    "k": "kk",
    "g": "kk",
    "ky": "kk",
    "gy": "kk",
    "kw": "kk",
    "gw": "kk",
    "s": "SS",
    "z": "SS",
    "sh": "CH",
    "ch": "CH",
    "j": "CH",
    "ts": "CH",
    "n": "nn",
    "ny": "nn",
    "N": "nn",
    "r": "RR",
    "ry": "RR",
    "y": "ih",
    "w": "ou",
    "h": "SS",
    "hy": "SS",
    "sil": "sil",
    "pau": "sil",
}


def phoneme_viseme(phoneme: str) -> str | None:
    """The viseme of an OpenJTalk phoneme (devoiced vowels map like voiced ones); None for
    ``cl`` (a geminate closure takes its shape from the context)."""
    if phoneme.lower() in VOWELS:
        return VOWEL_VISEMES[VOWELS.index(phoneme.lower())]
    if phoneme == "cl":
        return None
    if phoneme not in _CONSONANT_VISEME:
        raise VisemeError(f"unknown OpenJTalk phoneme {phoneme!r}")
    return _CONSONANT_VISEME[phoneme]


def from_phonemes(
    phones: Sequence,
    *,
    fps: float = FPS,
    smoothing_s: float = 0.04,
    duration_s: float | None = None,
) -> VisemeTrack:
    """The text-driven track from an OpenJTalk phoneme timeline.

    Each phone sets its viseme's target to 1 (devoiced vowels 0.4, ``h`` the following
    vowel's shape at 0.5, ``cl`` holds the previous shape, ``N`` before p/b/m is PP), sampled
    at frame times; coarticulation is a Gaussian blur of the targets with SD ``smoothing_s``
    (symmetric: a text-driven track may anticipate). ``sil`` takes the remainder.
    """
    if not phones:
        raise VisemeError("empty phoneme timeline")
    end = duration_s if duration_s is not None else phones[-1].end
    times = np.arange(int(np.floor(end * fps)) + 1) / fps
    targets = np.zeros((len(times), len(VISEMES)))
    for i, phone in enumerate(phones):
        ph = phone.phoneme
        weight = 1.0
        nxt = phones[i + 1].phoneme if i + 1 < len(phones) else "sil"
        if ph in ("A", "I", "U", "E", "O"):
            viseme, weight = phoneme_viseme(ph), 0.4
        elif ph in ("h", "hy") and nxt.lower() in VOWELS:
            viseme, weight = phoneme_viseme(nxt), 0.5
        elif ph == "N" and nxt in ("p", "b", "m", "py", "by", "my"):
            viseme = "PP"
        elif ph == "cl":
            viseme = "PP" if nxt in ("p", "b", "py", "by") else None
            if viseme is None:
                prev = phones[i - 1].phoneme if i else "sil"
                viseme, weight = phoneme_viseme(prev) or "sil", 0.5
        else:
            viseme = phoneme_viseme(ph)
        if viseme == "sil":
            continue
        sel = (times >= phone.start) & (times < phone.end)
        targets[sel, VISEMES.index(viseme)] = np.maximum(
            targets[sel, VISEMES.index(viseme)], weight
        )
    if smoothing_s > 0:
        sigma = smoothing_s * fps
        radius = int(np.ceil(4 * sigma))
        kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma) ** 2)
        kernel /= kernel.sum()
        padded = np.pad(targets, ((radius, radius), (0, 0)))
        targets = np.stack(
            [np.convolve(padded[:, j], kernel, mode="valid") for j in range(targets.shape[1])],
            axis=1,
        )
    total = targets[:, 1:].sum(axis=1)
    over = total > 1
    targets[over, 1:] /= total[over, None]
    targets[:, 0] = 1 - targets[:, 1:].sum(axis=1)
    return VisemeTrack(times=times, weights=np.clip(targets, 0, 1))


