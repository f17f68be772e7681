"""Closed eyes stay closed: limits on the weights that move the eyelids together.

Blendshapes add linearly. ``eyeBlink`` alone brings the upper lid down onto the lower lid,
but a blink during a smile adds it to ``eyeSquint`` (which narrows the eye from both lids)
and ``cheekSquint`` (which raises the lower lid): on the default head a blink with both at
full strength drives the upper lid 7.7 mm through the lower one. ARKit rigs built by artists
carry corrective shapes for such combinations; a rig without them needs a rule.

The rule here works in weight space, so it holds wherever the weights go (the lab renderer,
the browser and VR players): at each frame, the gap between the lid margins - each upper
margin vertex and the lower one across from it, predicted from how far each target moves
them - may not close beyond where the blink alone closes it (pairs where the blink sweeps
at least half its largest travel: not the corners). When it would, the blink gives way
first (the eye is then shut by the squint and the blink together), then the other channels
that lower the upper lid (``eyeSquint``, ``eyeLookDown``), in proportion. Channels that
only raise the lower lid or the cheek keep their weight: a smiling face that blinks keeps
its raised cheeks.

It needs lid landmarks (``upper_lid_{left,right}``, ``lower_lid_{left,right}``; the margins
themselves from parts ``lid_upper_*`` / ``lid_lower_*`` where listed) and the side's
``eyeBlink`` target; an avatar without them is left to its own shapes (:func:`lid_model`
returns None) - a glTF avatar's artist-made shapes usually are made to combine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from facelab.stimuli.avatar.mesh import Avatar

__all__ = ["LidModel", "close_lids", "lid_model"]

SIDES = ("left", "right")


@dataclass(frozen=True)
class _Side:
    blink: int  # target index of eyeBlink{Side}
    closers: np.ndarray  # (C,) target indices, other than the blink, that lower the upper lid
    closure: np.ndarray  # (P, K) metres each target closes each margin pair's gap at full weight
    open_gap: np.ndarray  # (P,) metres between the margins at rest
    closed_gap: np.ndarray  # (P,) metres left by the blink alone (the tightest allowed)


@dataclass(frozen=True)
class LidModel:
    """Per side, how each target moves pairs of lid-margin vertices (upper, lower)."""

    sides: tuple[_Side, ...]


#: margin pairs count where the blink sweeps at least this share of its largest travel
#: (the lids' corners hardly move in a blink: a limit there would hold the whole blink back)
SWEPT = 0.5


def _margin_pairs(avatar: Avatar, side: str) -> list[tuple[int, int]]:
    """(upper, lower) vertex pairs: the landmarks above and below the pupil, and - when the
    avatar lists its lid margins (parts ``lid_upper_*`` / ``lid_lower_*``) - each upper
    margin vertex with the lower one nearest across."""
    up = avatar.landmarks.get(f"upper_lid_{side}")
    lo = avatar.landmarks.get(f"lower_lid_{side}")
    if up is None or lo is None:
        return []
    pairs = [(up, lo)]
    upper = avatar.parts.get(f"lid_upper_{side}")
    lower = avatar.parts.get(f"lid_lower_{side}")
    if upper is not None and lower is not None and len(lower):
        x = avatar.neutral[:, 0]
        for u in upper:
            pairs.append((int(u), int(lower[np.argmin(np.abs(x[lower] - x[u]))])))
    return pairs


def lid_model(avatar: Avatar) -> LidModel | None:
    """The lid limits of ``avatar`` measured from its targets at the lid margins; None when
    it has no lid landmarks or no blink target."""
    names = avatar.target_names
    index = {n: i for i, n in enumerate(names)}
    sides = []
    for side in SIDES:
        pairs = _margin_pairs(avatar, side)
        blink = index.get(f"eyeBlink{side.title()}")
        if not pairs or blink is None:
            continue
        up, lo = (np.array(p) for p in zip(*pairs, strict=True))
        lowers = -np.stack([avatar.targets[n][up, 1] for n in names], axis=1)  # (P, K)
        closure = lowers + np.stack([avatar.targets[n][lo, 1] for n in names], axis=1)
        open_gap = avatar.neutral[up, 1] - avatar.neutral[lo, 1]
        swept = (closure[:, blink] >= SWEPT * closure[:, blink].max()) & (open_gap > 0)
        if closure[:, blink].max() <= 0 or not np.any(swept):
            continue
        closers = np.array(
            [i for i in np.nonzero((lowers[swept] > 1e-4).any(axis=0))[0] if i != blink],
            dtype=int,
        )
        closure, open_gap = closure[swept].astype(float), open_gap[swept].astype(float)
        sides.append(_Side(blink, closers, closure, open_gap, open_gap - closure[:, blink]))
    return LidModel(tuple(sides)) if sides else None


def close_lids(weights: np.ndarray, model: LidModel | None) -> tuple[np.ndarray, int]:
    """``weights`` (n_frames, K) with the lids limited (module doc), and the number of
    frames where a limit acted. Weights in [0, 1] in, weights in [0, 1] out."""
    out = np.array(weights, dtype=np.float64, copy=True)
    if model is None or out.size == 0:
        return out.astype(np.float32), 0
    limited = np.zeros(len(out), bool)
    for s in model.sides:
        excess = s.closed_gap[None, :] - (s.open_gap[None, :] - out @ s.closure.T)  # (n, P)
        over = (excess > 1e-5).any(axis=1)
        if not np.any(over):
            continue
        limited |= over
        ex = excess[over]
        per_blink = s.closure[:, s.blink]  # (P,) > 0 where swept
        # the blink gives way until no pair passes its closed gap
        give = np.minimum(np.max(ex / per_blink, axis=1), out[over, s.blink])
        out[over, s.blink] -= give
        rest = ex - give[:, None] * per_blink[None, :]  # (m, P)
        if s.closers.size:
            # what the blink could not give, the other closers give, all in one proportion
            shut = out[np.ix_(over, s.closers)] @ np.maximum(s.closure[:, s.closers], 0).T
            need = np.where(rest > 1e-9, rest / np.maximum(shut, 1e-12), 0.0).max(axis=1)
            out[np.ix_(over, s.closers)] *= np.clip(1.0 - need, 0.0, 1.0)[:, None]
    np.clip(out, 0.0, 1.0, out=out)
    return out.astype(np.float32), int(limited.sum())
