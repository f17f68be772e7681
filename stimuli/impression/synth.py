"""A SYNTHETIC expression database for impression models (no 3D face database can be
downloaded here), and simulated validation ratings - for demos and tests, clearly labelled.

:func:`synthetic_samples` builds, on the default head's ARKit rig, ``people`` people × the
seed's 8 expressions (a, i, u, e, o, neutral, closed-mouth smile, open-mouth smile):

* each expression's prototype (vowels: the shipped standard Z; smiles: written here), scaled
  per person and channel (gain ~ N(1, 0.15)), plus a person's own resting face (the neutral
  row, |N(0, 0.04)|, added to all of that person's rows) and noise N(0, 0.02);
* a latent impression z ~ N(0, 1) per person and expression, expressed in the face along a
  **known true direction** t (cheek and eye squint, smile, dimples, inner brow raise; unit,
  ARKit space) by 0.12·z·t;
* labels from a simulated first rating study: ``friendly_rating`` = 50 + 15·z + N(0, 6) on a
  0–100 scale, and ``friendly`` = high/low split at each expression's median rating.

Everything is clipped to [0, 1]. The true direction is returned (and written beside the CSV by
``facelab impression synth``) so a fit can be checked against it.

:func:`simulate_validation` plays a second, validation study: raters see the rendered peak
face at each level and rate how friendly it looks, 50 + β·(the face's displacement from the
expression's mean projected on t, in SDs of the database's projections) + rater offset + noise.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.capture.zmatrix import load_z
from facelab.stimuli.impression.model import ImpressionModel

__all__ = ["EXPRESSIONS", "TRUE_DIRECTION", "simulate_validation", "synthetic_samples"]

EXPRESSIONS = ("a", "i", "u", "e", "o", "neutral", "closed_smile", "open_smile")

_SMILES = {
    "closed_smile": {
        "mouthSmileLeft": 0.55, "mouthSmileRight": 0.55, "cheekSquintLeft": 0.25,
        "cheekSquintRight": 0.25, "mouthPressLeft": 0.15, "mouthPressRight": 0.15,
        "eyeSquintLeft": 0.15, "eyeSquintRight": 0.15,
    },
    "open_smile": {
        "mouthSmileLeft": 0.6, "mouthSmileRight": 0.6, "jawOpen": 0.3,
        "mouthUpperUpLeft": 0.3, "mouthUpperUpRight": 0.3, "mouthLowerDownLeft": 0.25,
        "mouthLowerDownRight": 0.25, "cheekSquintLeft": 0.3, "cheekSquintRight": 0.3,
        "eyeSquintLeft": 0.2, "eyeSquintRight": 0.2,
    },
}  # fmt: skip

_TRUTH = {
    "cheekSquintLeft": 0.45, "cheekSquintRight": 0.45, "eyeSquintLeft": 0.3,
    "eyeSquintRight": 0.3, "mouthSmileLeft": 0.35, "mouthSmileRight": 0.35,
    "mouthDimpleLeft": 0.25, "mouthDimpleRight": 0.25, "browInnerUp": 0.2,
}  # fmt: skip
_t = np.array([_TRUTH.get(n, 0.0) for n in ARKIT_NAMES])
#: the known impression direction of the synthetic database (unit, ARKit order)
TRUE_DIRECTION = _t / np.linalg.norm(_t)


def _prototype(expression: str) -> np.ndarray:
    if expression == "neutral":
        return np.zeros(52)
    if expression in _SMILES:
        return np.array([_SMILES[expression].get(n, 0.0) for n in ARKIT_NAMES])
    z = load_z("standard")
    return z[:, "aiueo".index(expression)].copy()


def synthetic_samples(*, people: int = 40, rng: np.random.Generator) -> pd.DataFrame:
    """The database as a DataFrame with columns ``person, expression, friendly,
    friendly_rating, <52 ARKit names>`` (the CSV ``facelab impression fit`` reads)."""
    rows = []
    for p in range(1, people + 1):
        person = f"synth{p:02d}"
        gain = rng.normal(1.0, 0.15, 52).clip(0.5, 1.5)
        resting = np.abs(rng.normal(0.0, 0.04, 52))
        ratings = {}
        faces = {}
        for e in EXPRESSIONS:
            if e == "neutral":
                faces[e] = resting
                ratings[e] = np.nan
                continue
            z = rng.normal()
            face = resting + _prototype(e) * gain + 0.12 * z * TRUE_DIRECTION
            faces[e] = np.clip(face + rng.normal(0.0, 0.02, 52), 0.0, 1.0)
            ratings[e] = float(np.clip(50 + 15 * z + rng.normal(0, 6), 0, 100))
        for e in EXPRESSIONS:
            rows.append(
                {
                    "person": person,
                    "expression": e,
                    "friendly_rating": ratings[e],
                    **dict(zip(ARKIT_NAMES, faces[e], strict=True)),
                }
            )
    df = pd.DataFrame(rows)
    medians = df[df.expression != "neutral"].groupby("expression").friendly_rating.median()
    df["friendly"] = [
        "" if e == "neutral" else ("high" if r > medians[e] else "low")
        for e, r in zip(df.expression, df.friendly_rating, strict=True)
    ]
    df["friendly_rating"] = df.friendly_rating.round(2)
    df[list(ARKIT_NAMES)] = df[list(ARKIT_NAMES)].round(5)
    return df[["person", "expression", "friendly", "friendly_rating", *ARKIT_NAMES]]


def simulate_validation(
    model: ImpressionModel,
    *,
    expression: str,
    levels: list[float],
    raters: int = 20,
    beta: float = 12.0,
    noise_sd: float = 8.0,
    rater_sd: float = 8.0,
    truth: np.ndarray = TRUE_DIRECTION,
    rng: np.random.Generator,
) -> pd.DataFrame:
    """Simulated ratings (0–100) of the peak face at each level: one row per rater and
    level, columns ``rater, expression, q, q_realised, perceived, rating, simulated``."""
    m = model.model(expression)
    env = np.array([0.0, 1.0])  # neutral, then the full expression
    sd = m.delta if m.delta > 0 else 1.0
    offsets = rng.normal(0.0, rater_sd, raters)

    def projection(q: float) -> tuple[float, dict]:
        frames, info = model.frames(expression, q, env)
        return float((frames[-1] - model.neutral_mean) @ truth), info

    base_proj, _ = projection(0.0)
    rows = []
    for q in levels:
        proj, info = projection(q)
        perceived = (proj - base_proj) / sd
        for r in range(raters):
            rating = float(
                np.clip(50 + beta * perceived + offsets[r] + rng.normal(0, noise_sd), 0, 100)
            )
            rows.append({"rater": f"R{r + 1:02d}", "expression": expression, "q": q,
                         "q_realised": info["q_realised"], "perceived": round(perceived, 4),
                         "rating": round(rating, 2), "simulated": True})  # fmt: skip
    return pd.DataFrame(rows)
