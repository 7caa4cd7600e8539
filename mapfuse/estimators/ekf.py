"""The EKF reference (:mod:`ekf_reference`) as a harness estimator."""

from __future__ import annotations

import dataclasses

import numpy as np

from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from ekf_reference.result import EKFResult
from mapfuse.estimator import Progress
from mapfuse.result import Anchor, EstimatorResult, MapEstimate, PoseTrack
from mapfuse_core.data.measlog import MeasurementLog

__all__ = ["EKFEstimator", "to_result"]


def to_result(res: EKFResult, log: MeasurementLog) -> EstimatorResult:
    """An :class:`EKFResult` of ``log`` as an :class:`EstimatorResult` (filtered poses)."""
    gm = res.global_map
    anchor = None
    if res.anchor is not None:
        a = res.anchor
        anchor = Anchor(a.x_Wknown_Wglobal, a.cov, int(a.accepted_at_step), a.pairings)
    return EstimatorResult(
        estimator="ekf",
        scenario=log.scenario,
        seed=log.seed,
        fusion=bool(res.config.fusion),
        timestamps=np.asarray(log.timestamps[: res.poses.shape[0]], dtype=float),
        step_time_s=res.step_time_s,
        map=MapEstimate(gm.kinds, gm.params, gm.covs, gm.known_ids, gm.true_ids, gm.n_obs),
        filtered=PoseTrack(res.poses, res.covs),
        anchor=anchor,
        decisions=res.decisions,
        extras={"ekf": res},
    )


class EKFEstimator:
    """Chanier et al.'s multi-map EKF with known-map fusion; options: :class:`EKFConfig`."""

    name = "ekf"
    options_type = EKFConfig

    def run(
        self,
        log: MeasurementLog,
        options: EKFConfig,
        *,
        fusion: bool,
        progress: Progress | None = None,
    ) -> EstimatorResult:
        """Run the EKF with ``options`` (its ``fusion`` set to ``fusion``)."""
        if not isinstance(options, EKFConfig):
            raise TypeError(f"the ekf estimator takes an EKFConfig, got {type(options).__name__}")
        res = run_ekf(log, dataclasses.replace(options, fusion=fusion), progress=progress)
        return to_result(res, log)
