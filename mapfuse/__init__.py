"""The mapfuse harness: runs any registered estimator on a measurement log, scores it,
compares estimators, keeps regression baselines, draws the figures, and the CLI.

The only package that knows every estimator.  Modules:

* :mod:`mapfuse.estimator` — the :class:`~mapfuse.estimator.Estimator` protocol;
* :mod:`mapfuse.result` — :class:`~mapfuse.result.EstimatorResult`, what every
  estimator returns;
* :mod:`mapfuse.registry` — estimators by name (``mapfuse.estimators`` entry points,
  :func:`~mapfuse.registry.register`);
* :mod:`mapfuse.estimators` — the built-in ``ekf``, ``batch`` and ``isam2`` adapters, and
  ``fixedlag`` (an entry point, not one of the built-in comparison set);
* :mod:`mapfuse.profiles` — per-dataset default options;
* :mod:`mapfuse.run`, :mod:`mapfuse.outputs` — one run and its files;
* :mod:`mapfuse.metrics` — ``metrics.json``;
* :mod:`mapfuse.compare`, :mod:`mapfuse.figures`, :mod:`mapfuse.plotting` — the
  comparison, its report and figures;
* :mod:`mapfuse.spectrum` — RMSE and ANEES against the smoother's lag;
* :mod:`mapfuse.baseline`, :mod:`mapfuse.testing` — regression baselines;
* :mod:`mapfuse.cli` — the ``mapfuse`` command.

Nothing is imported here, so ``import mapfuse`` loads neither gtsam nor matplotlib.
"""
