"""The audio-visual timing functions shared by the simulated participants
(:mod:`facelab.experiment.simulate`) and the window fits (:mod:`facelab.analysis.timing`).
Pure numpy/scipy.

``x`` is the voice's offset against the face in ms (negative: the voice first).

* **simultaneity** ("were they in sync?"): ``P(in sync) = floor + (peak - floor) * exp(-(x -
  pss)^2 / (2 sigma^2))`` - the window of simultaneity as a scaled Gaussian above a ``floor``
  (the "in sync" answers given far outside the window: guesses, or a bias to say yes); its
  centre ``pss`` is the point of subjective simultaneity and its width the Gaussian's full
  width at half its height, ``2 sqrt(2 ln 2) sigma``;
* **temporal order** ("which came first?"): ``P(voice first) = lapse / 2 + (1 - lapse) *
  Phi((pss - x) / sigma)`` - a cumulative Gaussian falling as the voice comes later; its 50 %
  point is the PSS and its width the distance between its 25 % and 75 % points, ``2 * 0.6745
  sigma`` (twice the just-noticeable difference).

Every function broadcasts over ``x`` and the parameters.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike
from scipy import special

__all__ = [
    "FWHM_PER_SIGMA",
    "IQR_PER_SIGMA",
    "JUDGMENTS",
    "p_timing",
    "sigma_of_width",
]

#: full width at half maximum of a Gaussian, in SDs
FWHM_PER_SIGMA = float(2.0 * np.sqrt(2.0 * np.log(2.0)))
#: distance between the 25 % and 75 % points of a normal distribution, in SDs
IQR_PER_SIGMA = float(2.0 * special.ndtri(0.75))
JUDGMENTS = ("simultaneity", "temporal_order")


def sigma_of_width(judgment: str, width_ms: ArrayLike) -> np.ndarray:
    """The Gaussian's SD (ms) of a window ``width_ms`` wide, as each judgment defines width."""
    per = FWHM_PER_SIGMA if judgment == "simultaneity" else IQR_PER_SIGMA
    return np.asarray(width_ms, dtype=float) / per


def p_timing(
    judgment: str, x: ArrayLike, *, pss: ArrayLike, width: ArrayLike, third: ArrayLike,
    floor: ArrayLike = 0.0,
) -> np.ndarray:  # fmt: skip
    """P(the judged label) at offsets ``x`` (ms): P(in sync) for ``simultaneity`` (``third``
    = the peak, ``floor`` the level far from it), P(voice first) for ``temporal_order``
    (``third`` = the lapse rate)."""
    if judgment not in JUDGMENTS:
        raise ValueError(f"judgment {judgment!r}: one of {', '.join(JUDGMENTS)}")
    x = np.asarray(x, dtype=float)
    z = (x - np.asarray(pss, dtype=float)) / sigma_of_width(judgment, width)
    third = np.asarray(third, dtype=float)
    if judgment == "simultaneity":
        floor = np.asarray(floor, dtype=float)
        return floor + (third - floor) * np.exp(-0.5 * z**2)
    return third / 2 + (1 - third) * special.ndtr(-z)
