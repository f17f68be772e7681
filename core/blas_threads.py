"""One BLAS thread for loops of small numpy products.

OpenBLAS's worker threads spin for a while after every product, waiting for the next. A loop
of many small products - fitting every participant's psychometric or timing function,
simulating studies for power, deforming and lighting a mesh per frame - gains nothing from
them, and their spinning takes a whole core from whatever else runs. Measured here (2 cores,
`tests/test_sync.py`'s coverage study of 150 simulated participants, the fits run under
:func:`facelab.analysis.timing.window_table`): 45 s wall and 86 CPU-seconds with OpenBLAS's
default threads, 40 s and 40 CPU-seconds with one. The renderer holds BLAS to one thread
while it draws a clip for the same reason (llvmpipe's rasterisers need that core).
"""

from __future__ import annotations

import functools
import sys
from collections.abc import Callable
from contextlib import AbstractContextManager
from typing import ParamSpec, TypeVar

from threadpoolctl import ThreadpoolController

__all__ = ["on_one_blas_thread", "one_blas_thread"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


_controller: tuple[int, ThreadpoolController] | None = None


def _blas_controller() -> ThreadpoolController:
    """threadpoolctl's view of the process's thread pools, found again only when modules
    were imported since (one may have loaded a BLAS: SciPy brings its own). Finding them
    walks every loaded shared library, 3.4 ms here; a power simulation enters the context
    once a study and a render once a clip."""
    global _controller
    if _controller is None or _controller[0] != len(sys.modules):
        _controller = (len(sys.modules), ThreadpoolController())
    return _controller[1]


def one_blas_thread() -> AbstractContextManager[object]:
    """A context in which numpy's BLAS (OpenBLAS, MKL, ...) uses one thread; the previous
    limits come back on leaving it. The limit is the whole process's: not for threads that
    enter and leave it concurrently (their exits may restore each other's limits - a matter
    of speed only, never of results)."""
    return _blas_controller().limit(limits=1, user_api="blas")


def on_one_blas_thread(func: Callable[_P, _R]) -> Callable[_P, _R]:
    """Decorator: ``func`` runs inside :func:`one_blas_thread`."""

    @functools.wraps(func)
    def held(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        with one_blas_thread():
            return func(*args, **kwargs)

    return held
