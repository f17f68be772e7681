"""Dynamic time warping between two feature sequences (pure numpy).

:func:`dtw_path` finds the monotone path through the frame-distance matrix with the least
summed cost, steps (1, 1), (1, 0) and (0, 1), both ends anchored. Each row of the cumulative
cost is computed at once: with a_j = min(D[i-1, j-1], D[i-1, j]) and S the running sum of the
row's costs, D[i, j] = S_j + min_{k <= j}(a_k − S_{k−1}) - a running minimum, so a 1000 × 1000
alignment takes milliseconds rather than a Python loop per cell.
"""

from __future__ import annotations

import numpy as np

__all__ = ["dtw_path"]


def dtw_path(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, float]:
    """Path (P, 2) of (index into a, index into b) pairs from (0, 0) to (len(a)-1, len(b)-1),
    and the mean frame distance along it. ``a`` (N, D) and ``b`` (M, D): Euclidean distances."""
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    n, m = len(a), len(b)
    if n == 0 or m == 0:
        raise ValueError("dtw_path: empty sequence")
    cost = np.sqrt(
        np.maximum((a * a).sum(1)[:, None] + (b * b).sum(1)[None, :] - 2.0 * (a @ b.T), 0.0)
    ).astype(np.float32)
    acc = np.empty_like(cost)
    acc[0] = np.cumsum(cost[0])
    for i in range(1, n):
        prev = acc[i - 1]
        diag = np.concatenate([[np.inf], prev[:-1]])
        a_j = np.minimum(diag, prev)
        s = np.cumsum(cost[i])
        s_prev = np.concatenate([[0.0], s[:-1]])
        acc[i] = s + np.minimum.accumulate(a_j - s_prev)
    path = [(n - 1, m - 1)]
    i, j = n - 1, m - 1
    while i > 0 or j > 0:
        if i == 0:
            j -= 1
        elif j == 0:
            i -= 1
        else:
            options = (acc[i - 1, j - 1], acc[i - 1, j], acc[i, j - 1])
            k = int(np.argmin(options))
            i, j = (i - 1, j - 1) if k == 0 else (i - 1, j) if k == 1 else (i, j - 1)
        path.append((i, j))
    path_arr = np.array(path[::-1])
    return path_arr, float(cost[path_arr[:, 0], path_arr[:, 1]].mean())
