"""The :class:`Estimator` protocol: what the harness needs from an estimator.

An estimator has a registered :attr:`~Estimator.name`, an options type whose
no-argument instance holds its defaults (per-dataset defaults come from
:mod:`mapfuse.profiles`), and a :meth:`~Estimator.run` that turns a measurement log
into an :class:`~mapfuse.result.EstimatorResult`.  Register one with
:func:`mapfuse.registry.register` or the ``mapfuse.estimators`` entry-point group
(``docs/plugins.md``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol, runtime_checkable

from mapfuse.result import EstimatorResult
from mapfuse_core.measlog import MeasurementLog

__all__ = ["Estimator", "Progress"]

#: ``progress(k, n)``: ``k`` of ``n`` steps done.
Progress = Callable[[int, int], None]


@runtime_checkable
class Estimator(Protocol):
    """An estimator the harness can run, compare and baseline.

    Optional attribute ``consumes``: the name of another estimator whose result this
    one takes as its options' ``upstream`` field (the graph backends consume the
    EKF's association decisions); :func:`mapfuse.compare.compare` then runs that
    estimator once per fusion setting and hands its result to every consumer.
    """

    name: str
    """Registered name (``--backend NAME``, ``metrics.json``'s ``backend``)."""
    options_type: type[Any]
    """Type of :meth:`run`'s ``options``; ``options_type()`` holds the defaults."""

    def run(
        self,
        log: MeasurementLog,
        options: Any,
        *,
        fusion: bool,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Estimate ``log``.

        ``fusion``: whether to fuse the log's known map; the harness passes ``True``
        only for a log that has one.  ``progress(k, n)`` may be called after each step.
        """
        ...
