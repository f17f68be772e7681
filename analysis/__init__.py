"""facelab.analysis: session logs -> one tidy table -> statistics, figures and reports.

:func:`run` is the one pipeline (:mod:`facelab.analysis.pipeline`) that ``facelab analyze``,
``facelab demo`` and the benchmarks use. It is loaded on first use, so importing a single
module such as :mod:`facelab.analysis.stats` does not load the report's plotting stack.
"""

from __future__ import annotations

from typing import Any

__all__ = ["AnalysisRun", "run"]


def __getattr__(name: str) -> Any:
    if name in __all__:
        from facelab.analysis import pipeline

        return getattr(pipeline, name)
    raise AttributeError(f"module 'facelab.analysis' has no attribute {name!r}")
