"""The GTSAM mirror of the paper's problem.

Modules, imported on demand (each loads gtsam):

* :mod:`mapfuse_graph.factors` — line and circle observation factors and the
  known-map anchor, on the measurement models of :mod:`mapfuse_core.geometry.features`;
* :mod:`mapfuse_graph.graph` — builds the factor graph from a measurement log
  (:mod:`~mapfuse_graph.builder`, :mod:`~mapfuse_graph.keys`, :mod:`~mapfuse_graph.options`,
  :mod:`~mapfuse_graph.validation`, :mod:`~mapfuse_graph.estimate`,
  :mod:`~mapfuse_graph.own_association`);
* :mod:`mapfuse_graph.solvers` — :func:`~mapfuse_graph.solvers.run_graph` over batch
  Levenberg–Marquardt (:mod:`~mapfuse_graph.batch`) and iSAM2 (:mod:`~mapfuse_graph.isam2`),
  with :mod:`~mapfuse_graph.marginals` and :mod:`~mapfuse_graph.results`.

Depends on :mod:`mapfuse_core` only (association decisions arrive as
:class:`~mapfuse_core.estimate.decisions.AssociationDecisions`); the harness that runs it beside
the EKF is :mod:`mapfuse`.
"""
