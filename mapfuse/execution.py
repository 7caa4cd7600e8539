"""One estimator on one log, its inputs given: :func:`estimate`, and the fusion rule
every run obeys (:func:`fusion_for`).

Below the planner (:mod:`mapfuse.plan`), which decides which runs to make and hands
each consumer its upstream; :func:`mapfuse.run` is the front door above both.
"""

from __future__ import annotations

from typing import Any

from mapfuse.estimator import Estimator, Progress
from mapfuse.options import make_options, override_options
from mapfuse.registry import resolve
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.measlog import MeasurementLog

__all__ = ["estimate", "fusion_for"]


def fusion_for(log: MeasurementLog, fusion: bool) -> bool:
    """Whether a run of ``log`` asked for ``fusion`` fuses anything: never without a
    known map (Victoria Park), whatever it asked.  Runs are made, and reported, so."""
    return bool(fusion) and len(log.known_map) > 0


def estimate(
    log: MeasurementLog,
    estimator: str | Estimator,
    *,
    fusion: bool = True,
    options: Any = None,
    upstream: EstimatorResult | None = None,
    progress: Progress | None = None,
    **overrides: Any,
) -> EstimatorResult:
    """One estimator's result on ``log``, with ``upstream`` (the result it consumes, if
    it consumes one) given: no planning, no metrics.  Options as for :func:`run`."""
    est = resolve(estimator)
    if options is None:
        options = make_options(est, log, **overrides)
    elif overrides:
        options = override_options(options, est.name, **overrides)
    if not isinstance(options, est.options_type):
        raise TypeError(
            f"the {est.name} estimator takes {est.options_type.__name__} options, "
            f"got {type(options).__name__}"
        )
    consumed = est.capabilities.consumes
    if upstream is not None and consumed is None:
        raise ValueError(f"the {est.name} estimator consumes no other estimator's result")
    fuse = fusion_for(log, fusion) and est.capabilities.fuses
    if upstream is not None and (upstream.estimator != consumed or upstream.fusion != fuse):
        raise ValueError(
            f"the {est.name} estimator consumes a {consumed} run "
            f"{'with' if fuse else 'without'} fusion, got a {upstream.estimator} run "
            f"{'with' if upstream.fusion else 'without'} fusion"
        )
    kwargs: dict[str, Any] = {"fusion": fuse, "progress": progress}
    if consumed is not None:
        kwargs["upstream"] = upstream
    result = est.run(log, options, **kwargs)
    if not isinstance(result, EstimatorResult):
        raise TypeError(
            f"the {est.name} estimator returned {type(result).__name__}, not an EstimatorResult"
        )
    return result
