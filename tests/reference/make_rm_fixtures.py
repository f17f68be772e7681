"""Writes the repeated-measures fixtures rm3.csv and rm4.csv (run once; outputs committed).

rm3: 8 participants x 3 conditions x 4 ratings per cell, VAS-like (0..100, 1 decimal), with
participant-specific condition effects so that sphericity is visibly violated.
rm4: 10 participants x 4 conditions x 1 rating.
The R script stats_reference.R computes the reference values from these files.
"""

from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).parent


def rm3(rng: np.random.Generator) -> pd.DataFrame:
    rows = []
    effects = {"baseline": 0.0, "standard": 12.0, "emphasized": 5.0}
    for p in range(1, 9):
        offset = rng.normal(0, 10)
        slope = rng.normal(0, 6)  # participant x condition interaction, unequal by condition
        for ci, (cond, eff) in enumerate(effects.items()):
            for rep in range(1, 5):
                value = 45 + offset + eff + slope * ci * ci / 2 + rng.normal(0, 9)
                rows.append((f"P{p:02d}", cond, rep, round(float(np.clip(value, 0, 100)), 1)))
    return pd.DataFrame(rows, columns=["participant", "condition", "repetition", "rating"])


def rm4(rng: np.random.Generator) -> pd.DataFrame:
    rows = []
    for p in range(1, 11):
        offset = rng.normal(0, 8)
        for ci, cond in enumerate(["c1", "c2", "c3", "c4"]):
            value = 50 + offset + 4 * ci + rng.normal(0, 3 + 3 * ci)
            rows.append((f"S{p:02d}", cond, 1, round(float(value), 2)))
    return pd.DataFrame(rows, columns=["participant", "condition", "repetition", "rating"])


if __name__ == "__main__":
    rng = np.random.default_rng(61)
    rm3(rng).to_csv(HERE / "rm3.csv", index=False)
    rm4(rng).to_csv(HERE / "rm4.csv", index=False)
