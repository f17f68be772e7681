"""Z matrices (52 ARKit rows x 5 vowel columns a, i, u, e, o): the shipped ones and CSV files."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from facelab.errors import StageError
from facelab.methods import BUILTIN_Z
from facelab.resources import package_file
from facelab.stimuli.arkit import ARKIT_NAMES
from facelab.stimuli.speech.track import VOWELS
from facelab.textfiles import read_rows

__all__ = ["DATA", "load_z"]

DATA = package_file("facelab.stimuli", "data")


def load_z(z: str, *, base_dir: Path = Path(".")) -> np.ndarray:
    """A Z matrix (52, 5): a shipped name (standard, emphasized) or a CSV path with a
    ``blendshape`` column of ARKit names and columns a, i, u, e, o in [0, 1]."""
    path = DATA / f"z_{z}.csv" if z in BUILTIN_Z else base_dir / z
    rows = read_rows(path, what="Z matrix", required=("blendshape", *VOWELS))
    if not rows or set(rows[0]) != {"blendshape", *VOWELS}:
        raise StageError(f"{path}: expected columns blendshape, a, i, u, e, o")
    by_name = {r["blendshape"]: r for r in rows}
    twice = sorted(n for n, k in Counter(r["blendshape"] for r in rows).items() if k > 1)
    if twice:
        raise StageError(f"{path}: rows given twice: {', '.join(twice[:5])}")
    missing = [n for n in ARKIT_NAMES if n not in by_name]
    unknown = [n for n in by_name if n not in ARKIT_NAMES]
    if missing or unknown:
        raise StageError(f"{path}: missing ARKit rows {missing[:5]} / unknown rows {unknown[:5]}")
    line = {r["blendshape"]: i for i, r in enumerate(rows, start=2)}  # the header is line 1
    for name in ARKIT_NAMES:
        for v in VOWELS:
            cell = by_name[name][v]
            try:
                float(cell)
            except (TypeError, ValueError):  # TypeError: a row with too few cells
                shown = "missing" if cell is None or not str(cell).strip() else repr(cell)
                raise StageError(
                    f"{path}: line {line[name]} ({name}), column {v}: {shown} is not a number "
                    "(expected a coefficient in [0, 1])"
                ) from None
    z_mat = np.array([[float(by_name[n][v]) for v in VOWELS] for n in ARKIT_NAMES])
    outside = ~((z_mat >= 0) & (z_mat <= 1))  # NaN is outside too
    if outside.any():
        r, c = np.argwhere(outside)[0]
        raise StageError(
            f"{path}: row {ARKIT_NAMES[r]}, column {VOWELS[c]}: {z_mat[r, c]:g} is outside "
            "[0, 1] (every value must lie in [0, 1])"
        )
    return z_mat
