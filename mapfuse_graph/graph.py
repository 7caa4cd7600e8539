"""The factor graph over a measurement log: the public names of its construction.

The graph is built by :class:`~mapfuse_graph.builder.GraphBuilder` (the overview of its
factors, fusion and association sources is in :mod:`mapfuse_graph.builder`), from
:mod:`mapfuse_graph.keys` (variable keys), :mod:`mapfuse_graph.options`
(:class:`GraphOptions`), :mod:`mapfuse_graph.validation` (log checks),
:mod:`mapfuse_graph.estimate` (what the builder reads from a solver) and
:mod:`mapfuse_graph.own_association`.  This module re-exports their public names.
"""

from __future__ import annotations

from mapfuse_graph.builder import GraphBuilder
from mapfuse_graph.estimate import Estimate, StepGraph
from mapfuse_graph.keys import anchor_key, known_key, landmark_key, pose_key, radius_key
from mapfuse_graph.options import ASSOCIATIONS, AssociationName, GraphOptions
from mapfuse_graph.validation import centre_radius_correlated, odometry_noise_cov

__all__ = [
    "ASSOCIATIONS",
    "AssociationName",
    "Estimate",
    "GraphBuilder",
    "GraphOptions",
    "StepGraph",
    "anchor_key",
    "centre_radius_correlated",
    "known_key",
    "landmark_key",
    "odometry_noise_cov",
    "pose_key",
    "radius_key",
]
