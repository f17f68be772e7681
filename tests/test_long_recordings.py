"""Long recordings are analysed in chunks (a 5-minute file took 2.5 GB in validate): the
results are those of one pass over the whole file (to rounding)."""

from __future__ import annotations

import numpy as np
import pytest

from facelab.stimuli.speech.analyser import raw_features
from facelab.stimuli.speech.features import FrameGeometry, frame_features
from facelab.stimuli.speech.not_speech import CHUNK_FRAMES, not_speech_reason

RATE = 48_000


@pytest.mark.parametrize("frames", [1999, 2000, 2001, 2500, 4001])
def test_features_in_chunks_are_the_whole_passes(frames: int) -> None:
    """To the last bits (matrix products round by their row count), also where a fixed
    chunk would leave one frame over (2001, 4001)."""
    geo = FrameGeometry.for_rate(RATE)
    n = (frames - 1) * geo.hop + 1
    x = np.random.default_rng(frames).normal(0, 0.1, n).astype(np.float32)
    _, chunked = raw_features(x, sample_rate=RATE)
    padded = np.concatenate([np.zeros(geo.win // 2), x.astype(np.float64), np.zeros(geo.win)])
    whole = frame_features(padded, geo, 0, (len(x) - 1) // geo.hop + 1)
    assert chunked.shape == whole.shape == (frames, whole.shape[1])
    assert np.allclose(chunked, whole, rtol=1e-12, atol=1e-12)


def test_a_tone_longer_than_a_chunk_is_still_found() -> None:
    seconds = 3 * CHUNK_FRAMES * 0.01  # three chunks of frames
    t = np.arange(int(seconds * RATE)) / RATE
    tone = 0.3 * np.sin(2 * np.pi * 440 * t)
    assert "a tone at 440 Hz" in (not_speech_reason(tone, sample_rate=RATE) or "")
    rng = np.random.default_rng(4)
    noise = rng.normal(0, 0.1, len(t))  # broadband: not a tone
    assert not_speech_reason(noise, sample_rate=RATE) is None
