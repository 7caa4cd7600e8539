"""One BLAS thread while a graph is solved.

GTSAM's own algebra is Eigen's; the numpy algebra around it (marginals, covariances)
works on small dense blocks, where more BLAS threads only contend for the cores
(docs/results/performance.md).  The limit is set around each run
and the caller's setting comes back after it, so a notebook or a script runs as fast
as the ``mapfuse`` command without setting anything.  (:mod:`ekf_reference` has its
own copy: the two packages share only :mod:`mapfuse_core`, which depends on numpy and
scipy alone.)
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import ParamSpec, TypeVar

from threadpoolctl import threadpool_limits

__all__ = ["single_threaded_blas"]

_P = ParamSpec("_P")
_R = TypeVar("_R")


def single_threaded_blas(fn: Callable[_P, _R]) -> Callable[_P, _R]:
    """``fn`` with every loaded BLAS library on one thread during each call."""

    @functools.wraps(fn)
    def limited(*args: _P.args, **kwargs: _P.kwargs) -> _R:
        # Made at each call: it limits the libraries loaded by then.
        with threadpool_limits(limits=1, user_api="blas"):
            return fn(*args, **kwargs)

    return limited
