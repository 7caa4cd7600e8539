"""Known-map change detection: which known features a run confirms, finds moved or
missing, and which mapped features are new (``docs/change-detection.md``).

It reads a run's decisions, trajectory and anchor and the log; it predicts the view
with the simulator's ray caster (:mod:`mapfuse_core.sim.laser`) and the extractor.
The true changes of a simulated map and the score of a report against them are
evaluation (:mod:`mapfuse_core.evaluation.change_truth`)."""

from mapfuse_core.changes.classify import classify_changes
from mapfuse_core.changes.consistency import (
    RunConsistency,
    consistency_from_innovations,
    no_consistency_evidence,
    withhold_changes,
)
from mapfuse_core.changes.evidence import (
    LandmarkEvidence,
    ObservationSet,
    observation_sets,
)
from mapfuse_core.changes.params import ChangeParams
from mapfuse_core.changes.report import (
    ChangeReport,
    ChangeStatus,
    FeatureChange,
    NewFeature,
)
from mapfuse_core.changes.residual import feature_residual, residual_dof
from mapfuse_core.changes.visibility import map_world, scans_in_view

__all__ = [
    "ChangeParams",
    "ChangeReport",
    "ChangeStatus",
    "FeatureChange",
    "LandmarkEvidence",
    "NewFeature",
    "ObservationSet",
    "RunConsistency",
    "classify_changes",
    "consistency_from_innovations",
    "feature_residual",
    "map_world",
    "no_consistency_evidence",
    "observation_sets",
    "residual_dof",
    "scans_in_view",
    "withhold_changes",
]
