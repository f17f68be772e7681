"""The intelligibility function of speech in noise, shared by the simulated listeners
(:mod:`facelab.experiment.simulate`) and the threshold fits (:mod:`facelab.analysis.srt`).
Pure numpy/scipy.

The probability of a right answer at signal-to-noise ratio ``x`` (dB)::

    P(x) = guess + (1 - guess - lapse) * logistic(beta * (x - m))

``guess`` is fixed by the task (1/k for a closed set of k words), ``lapse`` bounded. It is
parameterised by what the speech-in-noise literature reports: the **speech reception
threshold** ``srt`` - the SNR at which P = 1/2 (50 % words correct) - and the **slope** at
the SRT in proportion correct per dB; ``m`` and ``beta`` follow from them.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

__all__ = ["logistic_parameters", "p_correct"]


def logistic_parameters(
    *, srt: ArrayLike, slope: ArrayLike, guess: float, lapse: ArrayLike
) -> tuple[np.ndarray, np.ndarray]:
    """(m, beta) of the logistic whose P is 1/2 at ``srt`` with ``slope`` per dB there
    (needs ``guess + lapse < 1/2``)."""
    lapse = np.asarray(lapse, dtype=float)
    span = 1.0 - guess - lapse
    f = (0.5 - guess) / span  # the logistic's value at the SRT
    beta = np.asarray(slope, dtype=float) / (span * f * (1.0 - f))
    m = np.asarray(srt, dtype=float) - special.logit(f) / beta
    return m, beta


def p_correct(
    x: ArrayLike, *, srt: ArrayLike, slope: ArrayLike, guess: float, lapse: ArrayLike
) -> np.ndarray:
    """P(a right answer) at SNRs ``x`` (dB)."""
    m, beta = logistic_parameters(srt=srt, slope=slope, guess=guess, lapse=lapse)
    lapse = np.asarray(lapse, dtype=float)
    return guess + (1.0 - guess - lapse) * special.expit(beta * (np.asarray(x, float) - m))
