"""The GTSAM mirror of the paper's problem.

Modules, imported on demand (each loads gtsam):

* :mod:`mapfuse_graph.factors` — line and circle observation factors and the
  known-map anchor, on the measurement models of :mod:`mapfuse_core.features`;
* :mod:`mapfuse_graph.graph` — builds the factor graph from a measurement log;
* :mod:`mapfuse_graph.solvers` — batch Levenberg–Marquardt and iSAM2
  (:func:`~mapfuse_graph.solvers.run_graph`).

Depends on :mod:`mapfuse_core` only (association decisions arrive as
:class:`~mapfuse_core.decisions.AssociationDecisions`); the harness that runs it beside
the EKF is :mod:`mapfuse`.
"""
