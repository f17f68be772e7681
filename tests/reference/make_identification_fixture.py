"""Writes identification.csv (run once; output committed): 18 participants x 3 behaviour
conditions x 12 identification answers, "correct" drawn from a logistic model with a
participant intercept (so answers within a participant correlate), a condition effect and a
gesture-count covariate that varies within conditions. identification.R fits the reference
GEE with R's geepack.
"""

from pathlib import Path

import numpy as np
import pandas as pd

HERE = Path(__file__).parent


def main() -> None:
    rng = np.random.default_rng(20261123)
    effects = {"none": -0.4, "gestures_only": 0.0, "composite": 0.6}
    rows = []
    for p in range(1, 19):
        u = rng.normal(0, 0.7)
        for cond, eff in effects.items():
            for trial in range(1, 13):
                gestures = int(rng.integers(0, 6))
                eta = eff + u + 0.12 * (gestures - 2.5)
                correct = int(rng.random() < 1 / (1 + np.exp(-eta)))
                rows.append((f"P{p:02d}", cond, trial, gestures, correct))
    frame = pd.DataFrame(
        rows, columns=["participant", "condition", "trial", "n_gesture", "correct"]
    )
    frame.to_csv(HERE / "identification.csv", index=False)


if __name__ == "__main__":
    main()
