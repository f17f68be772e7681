"""Identification tasks: confusion matrices, accuracy, per-class recall and Cohen's kappa.

Input is tidy trial rows with the label a clip portrays (``target``) and the label chosen
(``response``); every function returns tidy DataFrames. Rows are the true labels, columns the
answers, both in the protocol's label order, so a matrix always has every label even when
nobody chose it.

Cohen's kappa is agreement beyond chance between the portrayed and the chosen labels::

    kappa = (p_o - p_e) / (1 - p_e),  p_o = sum_i C_ii / N,  p_e = sum_i (row_i * col_i) / N^2
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from facelab.analysis.stats import _require
from facelab.errors import AnalysisError

__all__ = ["SUMMARY_COLUMNS", "cohen_kappa", "confusion_matrix", "identification_summary"]

SUMMARY_COLUMNS = ("n", "accuracy", "chance", "kappa")


def confusion_matrix(
    trials: pd.DataFrame,
    *,
    labels: Sequence[str],
    target: str = "target",
    response: str = "response",
) -> pd.DataFrame:
    """Counts: index = portrayed label, columns = chosen label, both in ``labels`` order."""
    _require(trials, (target, response))
    unknown = sorted(set(trials[target]).union(trials[response]) - set(labels))
    if unknown:
        raise AnalysisError(f"labels {unknown} are not among the task's labels {list(labels)}")
    table = pd.crosstab(
        pd.Categorical(trials[target], categories=list(labels)),
        pd.Categorical(trials[response], categories=list(labels)),
        dropna=False,
    )
    table.index.name, table.columns.name = "target", "response"
    return table.astype(int)


def cohen_kappa(matrix: pd.DataFrame | np.ndarray) -> float:
    """Cohen's kappa of a square confusion matrix (NaN when chance agreement is 1)."""
    c = np.asarray(matrix, dtype=float)
    total = c.sum()
    if total == 0:
        return float("nan")
    p_o = np.trace(c) / total
    p_e = float(np.sum(c.sum(axis=1) * c.sum(axis=0))) / total**2
    return float("nan") if p_e >= 1.0 else float((p_o - p_e) / (1.0 - p_e))


def identification_summary(
    trials: pd.DataFrame,
    *,
    labels: Sequence[str],
    by: Sequence[str] = ("participant",),
    target: str = "target",
    response: str = "response",
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(summary, recall) per group of ``by`` and pooled (``by`` columns ``"pooled"``).

    ``summary``: ``[*by, n, accuracy, chance, kappa]`` - chance is 1 / number of labels.
    ``recall``: ``[*by, label, n, recall, precision]`` - recall = correct / portrayed;
    precision = correct / chosen (NaN when the label was never chosen).
    """
    _require(trials, (*by, target, response))
    groups = list(trials.groupby(list(by), sort=True)) if by else []
    summary, recall = [], []
    for key, part in [*groups, (("pooled",) * len(by), trials)]:
        key = key if isinstance(key, tuple) else (key,)
        ids = dict(zip(by, key, strict=True))
        m = confusion_matrix(part, labels=labels, target=target, response=response)
        c = m.to_numpy(dtype=float)
        n = c.sum()
        summary.append(
            {
                **ids,
                "n": int(n),
                "accuracy": float(np.trace(c) / n) if n else float("nan"),
                "chance": 1.0 / len(labels),
                "kappa": cohen_kappa(c),
            }
        )
        for i, label in enumerate(labels):
            shown, chosen = c[i].sum(), c[:, i].sum()
            recall.append(
                {
                    **ids,
                    "label": label,
                    "n": int(shown),
                    "recall": float(c[i, i] / shown) if shown else float("nan"),
                    "precision": float(c[i, i] / chosen) if chosen else float("nan"),
                }
            )
    return (
        pd.DataFrame(summary, columns=[*by, *SUMMARY_COLUMNS]),
        pd.DataFrame(recall, columns=[*by, "label", "n", "recall", "precision"]),
    )
