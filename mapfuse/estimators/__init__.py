"""Adapters of the built-in estimators to :class:`mapfuse.estimator.Estimator`.

Imported on demand through the registry: :mod:`mapfuse.estimators.ekf` never loads
gtsam; :mod:`mapfuse.estimators.graph` does.
"""
