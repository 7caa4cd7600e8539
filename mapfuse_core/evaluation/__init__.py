"""Evaluation shared by every backend: errors, NEES, the parts of a run's metrics, TUM files.

All backends report the vehicle pose ``x^Wglobal_R`` (``Wglobal`` = the vehicle at
step 0) with a covariance of the absolute ``(x, y, θ)`` perturbation, so one
function computes every metric from the same truth.
"""

from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.evaluation.metrics import (
    MapDrawOffset,
    PoseErrors,
    anchor_metrics,
    anchor_truth,
    gps_error_series,
    gps_position_metrics,
    interpolate_positions,
    known_map_draw_offset,
    nees_summary,
    path_length,
    pose_errors,
    pose_metrics,
    rigid_alignment,
    runtime_metrics,
    summary_stats,
    truth_in_global,
    write_tum,
)
from mapfuse_core.evaluation.nees import (
    CHI2_3_95,
    NeesMeanDistribution,
    consistent_error_draws,
    consistent_nees_draws,
    integrated_autocorrelation_time,
    joint_nees,
    nees_mean_distribution,
    nees_mean_interval,
    nees_series,
    pooled_nees_mean_distribution,
)

__all__ = [
    "CHI2_3_95",
    "MapDrawOffset",
    "NeesMeanDistribution",
    "PoseErrors",
    "anchor_metrics",
    "anchor_truth",
    "consistent_error_draws",
    "consistent_nees_draws",
    "gps_error_series",
    "gps_position_metrics",
    "integrated_autocorrelation_time",
    "interpolate_positions",
    "joint_nees",
    "known_map_draw_offset",
    "landmark_labels",
    "nees_mean_distribution",
    "nees_mean_interval",
    "nees_series",
    "nees_summary",
    "path_length",
    "pooled_nees_mean_distribution",
    "pose_errors",
    "pose_metrics",
    "rigid_alignment",
    "runtime_metrics",
    "summary_stats",
    "truth_in_global",
    "write_tum",
]
