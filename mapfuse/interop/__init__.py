"""Bridges from mapfuse's results to the tools researchers use with them.

* :mod:`mapfuse.interop.networkx` — CCDA's correspondence graph as a ``networkx.Graph``.

The TUM trajectories for evo are :mod:`mapfuse.trajectories`; the GTSAM graph and its
g2o export are :attr:`mapfuse_graph.results.GraphDetails.graph` and
:mod:`mapfuse_graph.export`.
"""
