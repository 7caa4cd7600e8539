"""Data association shared by every estimator: its settings, gates and searches.

* :mod:`mapfuse_core.matching.config` — :class:`AssociationConfig`, the one set of
  association settings the EKF and the factor graph both read;
* :mod:`mapfuse_core.matching.gating` — χ² gate, pre-gate, gap between collinear
  segments;
* :mod:`mapfuse_core.matching.search` — greedy nearest neighbour and JCBB over scored
  candidates, with the one-to-one rules, and the ambiguity rule of map pairings.

numpy and scipy only.
"""

from mapfuse_core.matching.config import MAP_AMBIGUITY, METHODS, AssociationConfig
from mapfuse_core.matching.gating import chi2_gate, line_gap, line_overhang, near, pregate
from mapfuse_core.matching.search import (
    Scored,
    ScoredPair,
    drop_ambiguous,
    jcbb,
    nearest_neighbour,
)

__all__ = [
    "MAP_AMBIGUITY",
    "METHODS",
    "AssociationConfig",
    "Scored",
    "ScoredPair",
    "chi2_gate",
    "drop_ambiguous",
    "jcbb",
    "line_gap",
    "line_overhang",
    "near",
    "nearest_neighbour",
    "pregate",
]
