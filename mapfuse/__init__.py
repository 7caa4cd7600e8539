"""mapfuse: the front door of the toolkit.

.. code-block:: python

    import mapfuse as mf

    log = mf.simulate("loop600", seed=0)        # or mf.load("carmen:intel.log.gz"), ...
    run = mf.run(log, "ekf")                    # a Run: result, metrics, errors, truth
    print(run.metrics.position_error.rmse, run.errors.rmse)
    run.plot()
    report = mf.compare(log, ["ekf", "batch"])  # every estimator on the same log

Everything here loads on first use, so ``import mapfuse`` loads neither gtsam nor
matplotlib.  The names and where they live:

* logs: :func:`simulate`, :func:`load` (:mod:`mapfuse.runner`);
* runs: :func:`run` → :class:`Run` (its :class:`RunErrors`, typed :class:`RunMetrics`);
* several estimators on one log: :func:`compare` → :class:`Comparison`
  (:mod:`mapfuse.comparison`); over seeds and worlds: :func:`montecarlo`
  (:mod:`mapfuse.campaign`);
* your own estimator: :class:`Estimator`, :class:`Capabilities`, :func:`register`
  (:mod:`mapfuse.estimator`, :mod:`mapfuse.registry`; ``docs/plugins.md``);
* what every estimator returns: :class:`EstimatorResult`, :class:`PoseTrack`,
  :class:`MapEstimate`, :class:`Anchor` (:mod:`mapfuse_core.estimate`).

The harness is the only package that knows every estimator (through the registry and
the capabilities each declares); ``mapfuse --help`` is its command line.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mapfuse.campaign.api import montecarlo
    from mapfuse.comparison import Comparison, compare
    from mapfuse.estimator import Capabilities, Estimator
    from mapfuse.registry import available, register
    from mapfuse.runner import Run, RunErrors, load, run, simulate
    from mapfuse_core.estimate import (
        Anchor,
        AssociationDecisions,
        EstimatorResult,
        MapEstimate,
        MatchAttempts,
        PoseTrack,
        RunMetrics,
    )

__all__ = [
    "Anchor",
    "AssociationDecisions",
    "Capabilities",
    "Comparison",
    "Estimator",
    "EstimatorResult",
    "MapEstimate",
    "MatchAttempts",
    "PoseTrack",
    "Run",
    "RunErrors",
    "RunMetrics",
    "available",
    "compare",
    "load",
    "montecarlo",
    "register",
    "run",
    "simulate",
]

#: Where each front-door name lives, imported on first use.
_LAZY: dict[str, str] = {
    "simulate": "mapfuse.runner",
    "load": "mapfuse.runner",
    "run": "mapfuse.runner",
    "Run": "mapfuse.runner",
    "RunErrors": "mapfuse.runner",
    "compare": "mapfuse.comparison",
    "Comparison": "mapfuse.comparison",
    "montecarlo": "mapfuse.campaign.api",
    "register": "mapfuse.registry",
    "available": "mapfuse.registry",
    "Estimator": "mapfuse.estimator",
    "Capabilities": "mapfuse.estimator",
    "EstimatorResult": "mapfuse_core.estimate",
    "PoseTrack": "mapfuse_core.estimate",
    "MapEstimate": "mapfuse_core.estimate",
    "Anchor": "mapfuse_core.estimate",
    "AssociationDecisions": "mapfuse_core.estimate",
    "MatchAttempts": "mapfuse_core.estimate",
    "RunMetrics": "mapfuse_core.estimate",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module 'mapfuse' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
