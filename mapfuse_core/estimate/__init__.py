"""What every estimator returns, below everything that makes or reads it.

:class:`EstimatorResult` holds a run's pose tracks (:class:`PoseTrack`), final map
(:class:`MapEstimate`), anchor in the known map (:class:`Anchor`), association
decisions (:class:`AssociationDecisions`) and map matchings (:class:`MatchAttempts`);
:class:`RunMetrics` is what a run's numbers say of it.
The EKF reference, the graph backends and any plug-in return it; metrics and
figures read nothing else.
"""

from mapfuse_core.estimate.anchor import Anchor
from mapfuse_core.estimate.decisions import (
    ASSOCIATIONS_FORMAT,
    AnchorDecision,
    AssociationDecisions,
    KnownMapGating,
    load_associations,
)
from mapfuse_core.estimate.map import MapEstimate
from mapfuse_core.estimate.matching import MatchAttempts
from mapfuse_core.estimate.metrics import (
    METRICS_SCHEMA_VERSION,
    AnchorMetrics,
    ErrorStats,
    HeadingError,
    MapMetrics,
    MatchingMetrics,
    NeesMeanInterval,
    NeesSummary,
    PositionError,
    RunMetrics,
    RuntimeMetrics,
)
from mapfuse_core.estimate.result import EstimatorResult
from mapfuse_core.estimate.track import PoseTrack

__all__ = [
    "ASSOCIATIONS_FORMAT",
    "METRICS_SCHEMA_VERSION",
    "Anchor",
    "AnchorDecision",
    "AnchorMetrics",
    "AssociationDecisions",
    "ErrorStats",
    "EstimatorResult",
    "HeadingError",
    "KnownMapGating",
    "MapEstimate",
    "MapMetrics",
    "MatchAttempts",
    "MatchingMetrics",
    "NeesMeanInterval",
    "NeesSummary",
    "PoseTrack",
    "PositionError",
    "RunMetrics",
    "RuntimeMetrics",
    "load_associations",
]
