"""The GTSAM mirror of the paper's problem, the comparison harness and the CLI.

Modules, imported on demand (each loads gtsam):

* :mod:`mapfuse_graph.factors` — line and circle observation factors and the
  known-map anchor, on the measurement models of :mod:`mapfuse_core.features`;
* :mod:`mapfuse_graph.graph` — builds the factor graph from a measurement log;
* :mod:`mapfuse_graph.solvers` — batch Levenberg–Marquardt and iSAM2
  (:func:`~mapfuse_graph.solvers.run_graph`);
* :mod:`mapfuse_graph.runner` — one entry point for every backend
  (:func:`~mapfuse_graph.runner.run_backend`) and the run's output files;
* :mod:`mapfuse_graph.compare`, :mod:`mapfuse_graph.figures`,
  :mod:`mapfuse_graph.baseline` — the comparison, its figures, EKF baselines;
* :mod:`mapfuse_graph.testing` — assert a run is no worse than a recorded baseline;
* :mod:`mapfuse_graph.cli` — the ``mapfuse`` command.
"""
