"""Frozen result of an EKF run: what metrics, plots and the graph backend consume."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from ekf_reference.config import EKFConfig
from mapfuse_core.estimate.decisions import AnchorDecision, AssociationDecisions, KnownMapGating
from mapfuse_core.geometry.se2 import FloatArray

__all__ = [
    "AnchorResult",
    "EKFResult",
    "LoopClosure",
    "MapResult",
]


@dataclass(frozen=True)
class AnchorResult:
    """The estimated pose of the SLAM frame in the known map (paper: [−28.968, −10.980, 1.0472])."""

    x_Wknown_Wglobal: FloatArray
    """(3,) pose of ``Wglobal`` (the vehicle at step 0) in ``Wknown``, at the end of the run."""
    cov: FloatArray
    """(3, 3) its covariance."""
    accepted_at_step: int
    """Step after whose join CCDA accepted the match."""
    pairings: tuple[tuple[int, int], ...]
    """CCDA pairings as (true world id of the estimated feature or −1, known-map id).  The
    feature's id is the one most of its observations up to the match carry
    (:func:`~mapfuse_core.evaluation.landmark_labels`)."""


@dataclass(frozen=True)
class MapResult:
    """The final global map in ``Wglobal``."""

    kinds: np.ndarray
    """(F,) int8 feature kinds (0 line, 1 circle)."""
    params: FloatArray
    """(F, 3) parameters in ``Wglobal``."""
    covs: FloatArray
    """(F, 3, 3) marginal covariances."""
    known_ids: np.ndarray
    """(F,) known-map id of features merged with the known map, −1 otherwise."""
    true_ids: np.ndarray
    """(F,) world id of the first observation (simulation; −1 unknown)."""
    n_obs: np.ndarray
    """(F,) number of observations fused."""
    tracks: np.ndarray | None = None
    """(F,) the landmark (track) id of each feature, as the decisions'
    ``obs_landmark`` give it; −1 for a known feature the filter only carries."""
    params_known: FloatArray | None = None
    """(F, 3) each feature kept apart from the known map, in ``Wknown`` (NaN for the
    known features, and everywhere without a match)."""
    covs_known: FloatArray | None = None
    """(F, 3, 3) their covariances, from each feature's joint marginal with the anchor
    (NaN where :attr:`params_known` is)."""


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """A loop closure found at a join by registering the local map's circles to the
    global map's (:mod:`ekf_reference.loops`; only with ``EKFConfig.loop_closure``)."""

    step: int
    """Step whose join found it."""
    inliers: int
    """Local circles the registration put on global ones."""
    inliers_at_identity: int
    """How many the filter's own relative pose of the two maps put on global ones."""
    runner_up: int
    """Inliers of the best distinct hypothesis."""
    pairings: int
    """Registered pairings that passed their (widened) gate and were applied."""
    correction: FloatArray
    """(3,) ``(dx, dy, dθ)``: how the registration moves the global map onto the local
    one, in the join's frame, about the centroid of the global inliers (m, m, rad).
    ``dθ`` of one sign on every closure means a systematic drift (e.g. a sensor's yaw)."""


@dataclass(frozen=True)
class EKFResult:
    """Per-step vehicle estimates, final map, anchor and association decisions."""

    scenario: str
    """Scenario name of the log."""
    seed: int
    """Seed of the log."""
    config: EKFConfig
    """Configuration used."""
    poses: FloatArray
    """(N, 3) filtered vehicle pose ``x^Wglobal_R`` at each step."""
    covs: FloatArray
    """(N, 3, 3) its covariance (absolute ``(x, y, θ)`` perturbation)."""
    poses_in_known: FloatArray
    """(N, 3) vehicle pose in ``Wknown`` from the local map's anchor (NaN before fusion)."""
    covs_in_known: FloatArray
    """(N, 3, 3) its covariance (NaN before fusion)."""
    step_time_s: FloatArray
    """(N,) wall time of each step, joins and CCDA included."""
    anchor: AnchorResult | None
    """The anchor, or ``None`` if CCDA never accepted a match (or fusion is off)."""
    global_map: MapResult
    """The final global map."""
    obs_landmark: np.ndarray
    """(M,) landmark (track) id of every logged observation after all merges."""
    obs_known_id: np.ndarray
    """(M,) known-map id the observation's landmark was merged with, −1 otherwise."""
    ccda_attempts: int
    """How many CCDA matchings were run."""
    loop_closures: tuple[LoopClosure, ...] = ()
    """Loop closures found at the joins, in order (none unless ``config.loop_closure``,
    and none once the known map is fused: the local maps are then held to it)."""
    ccda_reasons: Mapping[str, int] = field(default_factory=dict)
    """CCDA matchings per outcome (:attr:`~mapfuse_core.matching.ccda.CCDAResult.reason`;
    ``"jointly inconsistent"`` for a match CCDA accepted and the joint test of its
    pairings refused, ``"a pairing inconsistent with the others"`` for one that a
    pairing's own test refused); the counts sum to :attr:`ccda_attempts`."""
    ccda_refused: tuple[tuple[int, float, int], ...] = ()
    """``(step, χ², degrees of freedom)`` of each CCDA match the EKF refused: the χ² of
    all its pairings (:attr:`~mapfuse_core.matching.AssociationConfig.match_joint_test`)
    or of the pairing that failed its own test
    (:attr:`~mapfuse_core.matching.AssociationConfig.match_pairing_test`)."""
    ccda_excluded: tuple[tuple[int, int], ...] = ()
    """``(step, known id)`` of each pairing whose failure of its own test made the EKF
    match again at once without its map feature
    (:attr:`~mapfuse_core.matching.AssociationConfig.match_exclusions`); the refused
    match is in :attr:`ccda_refused`, and each re-run is a CCDA attempt of its own."""
    tentative_promoted: int = 0
    """Tentative features promoted to the map (``config.tentative_min_sightings`` > 1)."""
    tentative_dropped: int = 0
    """Tentative features dropped, never promoted; their observations are unassociated."""
    known_gating: KnownMapGating | None = None
    """The known-map gate's rejections and un-fused features (``None`` without fusion or
    with ``config.known_map_gating`` off)."""

    @property
    def decisions(self) -> AssociationDecisions:
        """The final association decisions (and the accepted match), as data another
        estimator consumes."""
        anchor = None
        if self.anchor is not None:
            anchor = AnchorDecision(
                np.asarray(self.anchor.x_Wknown_Wglobal, dtype=float),
                int(self.anchor.accepted_at_step),
            )
        return AssociationDecisions(self.obs_landmark, self.obs_known_id, anchor, self.known_gating)
