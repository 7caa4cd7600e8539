"""The EKF reference (:mod:`ekf_reference`) as a harness estimator."""

from __future__ import annotations

import dataclasses

import numpy as np

from ekf_reference.config import EKFConfig
from ekf_reference.pipeline import run_ekf
from ekf_reference.result import EKFResult
from mapfuse.estimator import Progress
from mapfuse.result import Anchor, EstimatorResult, MapEstimate, MatchAttempts, PoseTrack
from mapfuse_core.measlog import MeasurementLog

__all__ = ["EKFEstimator", "to_result"]


def to_result(res: EKFResult, log: MeasurementLog) -> EstimatorResult:
    """An :class:`EKFResult` of ``log`` as an :class:`EstimatorResult` (filtered poses).

    A known feature's ``n_obs`` is the number of logged observations associated with
    it (:attr:`EKFResult.obs_known_id`), as the graph's landmarks count theirs: the
    EKF's own count misses those absorbed into it by a hard constraint.
    """
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
        map=MapEstimate(
            gm.kinds,
            gm.params,
            gm.covs,
            gm.known_ids,
            gm.true_ids,
            _n_obs(res),
            tracks=gm.tracks,
            params_known=gm.params_known,
            covs_known=gm.covs_known,
        ),
        filtered=PoseTrack(res.poses, res.covs),
        anchor=anchor,
        decisions=res.decisions,
        matching=MatchAttempts(res.ccda_attempts, dict(res.ccda_reasons))
        if res.config.fusion
        else None,
        tentative_dropped=res.tentative_dropped,
        extras={"ekf": res},
    )


def _n_obs(res: EKFResult) -> np.ndarray:
    """Observations per map feature, those of known features from the decisions."""
    gm = res.global_map
    n_obs = np.array(gm.n_obs, dtype=np.int64, copy=True)
    known = np.asarray(gm.known_ids) >= 0
    if np.any(known):
        ids, counts = np.unique(res.obs_known_id[res.obs_known_id >= 0], return_counts=True)
        per_id = dict(zip(ids.tolist(), counts.tolist(), strict=True))
        n_obs[known] = [per_id.get(int(i), 0) for i in np.asarray(gm.known_ids)[known]]
    return n_obs


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
