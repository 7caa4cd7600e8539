"""Known-map change detection: which known features a run confirms, finds moved or
missing, and which mapped features are new (``docs/changes.md``)."""

from mapfuse_core.evaluation.changes.classify import classify_changes
from mapfuse_core.evaluation.changes.evidence import (
    LandmarkEvidence,
    ObservationSet,
    observation_sets,
)
from mapfuse_core.evaluation.changes.params import ChangeParams
from mapfuse_core.evaluation.changes.report import (
    ChangeReport,
    ChangeStatus,
    FeatureChange,
    NewFeature,
)
from mapfuse_core.evaluation.changes.residual import feature_residual, residual_dof
from mapfuse_core.evaluation.changes.visibility import map_world, scans_in_view

__all__ = [
    "ChangeParams",
    "ChangeReport",
    "ChangeStatus",
    "FeatureChange",
    "LandmarkEvidence",
    "NewFeature",
    "ObservationSet",
    "classify_changes",
    "feature_residual",
    "map_world",
    "observation_sets",
    "residual_dof",
    "scans_in_view",
]
