"""Metrics of an EKF run in the shared ``metrics.json`` schema."""

from __future__ import annotations

from typing import Any

from ekf_reference.result import EKFResult
from mapfuse_core.evaluation import anchor_block, build_metrics
from mapfuse_core.measlog import MeasurementLog

__all__ = ["ekf_metrics"]


def ekf_metrics(result: EKFResult, log: MeasurementLog) -> dict[str, Any]:
    """``metrics.json`` of an EKF run on ``log``."""
    anchor = anchor_block(result.anchor, log.true_poses, log.known_frame)
    return build_metrics(
        scenario=log.scenario,
        seed=log.seed,
        backend="ekf",
        fusion=log.fuses(result.config.fusion),
        poses=result.poses,
        covs=result.covs,
        true_poses=log.true_poses,
        step_time_s=result.step_time_s,
        anchor=anchor,
        map_features=len(result.global_map.kinds),
        matched_known=int((result.global_map.known_ids >= 0).sum()),
        timestamps=log.timestamps,
        gps=log.gps,
    )
