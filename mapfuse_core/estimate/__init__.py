"""What every estimator returns, below everything that makes or reads it."""

from mapfuse_core.estimate.decisions import (
    ASSOCIATIONS_FORMAT,
    AnchorDecision,
    AssociationDecisions,
    KnownMapGating,
    load_associations,
)

__all__ = [
    "ASSOCIATIONS_FORMAT",
    "AnchorDecision",
    "AssociationDecisions",
    "KnownMapGating",
    "load_associations",
]
