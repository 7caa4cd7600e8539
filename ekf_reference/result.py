"""What an EKF run reports beyond the :class:`~mapfuse_core.estimate.EstimatorResult`
every estimator returns: :class:`EKFDetails`, and its loop closures."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ekf_reference.anchor_watch import Contradiction
from ekf_reference.config import EKFConfig
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["EKFDetails", "InnovationTotals", "LoopClosure", "UndoneAnchor"]


@dataclass(frozen=True)
class InnovationTotals:
    """The observation updates' normalised innovations squared, summed over a run: for
    a consistent filter a χ² with :attr:`dof` degrees of freedom (the association's
    gate truncates the largest, which lowers it)."""

    chi2: float
    """``Σ rᵀ S⁻¹ r`` over every step's batched update with its measurements."""
    dof: int
    """Their summed residual dimensions (2 per line, 3 per circle)."""


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


@dataclass(frozen=True, eq=False)
class UndoneAnchor:
    """An anchor the anchor watch found contradicted after its fusion, and undid
    (:mod:`ekf_reference.anchor_watch`)."""

    fused_at_step: int
    """Step whose join fused the match; filtering went back to just before it."""
    undone_at_step: int
    """Step at whose end the watch found it contradicted."""
    test: Contradiction
    """The test that contradicted it."""
    statistic: float
    """That test's value (summed NIS, known features passed by, or pairings un-fused)."""
    threshold: float
    """What the statistic exceeded."""
    dof: int
    """Degrees of freedom of the summed NIS (0 for the counting tests)."""
    x_Wknown_Wglobal: FloatArray
    """(3,) the anchor as fused."""
    cov: FloatArray
    """(3, 3) its covariance as fused."""
    pairings: tuple[tuple[int, int], ...]
    """The match's pairings, as :attr:`mapfuse_core.estimate.Anchor.pairings`."""


@dataclass(frozen=True, eq=False)
class EKFDetails:
    """What only the EKF reference reports, beside its
    :class:`~mapfuse_core.estimate.EstimatorResult` (``result.details``)."""

    config: EKFConfig
    """Configuration used."""
    poses_in_known: FloatArray
    """(N, 3) vehicle pose in ``Wknown`` from the local map's anchor (NaN before fusion)."""
    covs_in_known: FloatArray
    """(N, 3, 3) its covariance (NaN before fusion)."""
    loop_closures: tuple[LoopClosure, ...] = ()
    """Loop closures found at the joins, in order (none unless ``config.loop_closure``,
    and none once the known map is fused: the local maps are then held to it)."""
    ccda_refused: tuple[tuple[int, float, int], ...] = ()
    """``(step, χ², degrees of freedom)`` of each CCDA match the EKF refused: the χ² of
    all its pairings (:attr:`~mapfuse_core.matching.AssociationConfig.match_joint_test`)
    or of the pairing that failed its own test
    (:attr:`~mapfuse_core.matching.AssociationConfig.match_pairing_test`).  The reasons
    are counted in the result's ``matching.reasons`` (``"jointly inconsistent"``, ``"a
    pairing inconsistent with the others"``)."""
    ccda_excluded: tuple[tuple[int, int], ...] = ()
    """``(step, known id)`` of each pairing whose failure of its own test made the EKF
    match again at once without its map feature
    (:attr:`~mapfuse_core.matching.AssociationConfig.match_exclusions`); the refused
    match is in :attr:`ccda_refused`, and each re-run is a CCDA attempt of its own."""
    tentative_promoted: int = 0
    """Tentative features promoted to the map (``config.tentative_min_sightings`` > 1);
    those dropped are the result's ``tentative_dropped``."""
    anchors_undone: tuple[UndoneAnchor, ...] = ()
    """Anchors the watch undid, in order (``config.anchor_watch``); each one's CCDA call
    is counted in ``matching.reasons`` as ``"anchor contradicted"``, and later matches
    compatible with it as ``"compatible with an undone anchor"``."""
    innovations: InnovationTotals = InnovationTotals(0.0, 0)
    """The measurement updates' innovations over the run: the consistency evidence of
    a run without a reference trajectory (``mapfuse.changes.run_consistency``)."""
    joins: int = 0
    """Local maps joined into the global map over the run, the last one included (a
    join made again after an anchor is undone counts again): how
    ``config.local_map_steps`` and ``config.local_map_heading_sigma_rad`` cut the run."""
    increment_unconverged: int = 0
    """Steps whose update through the odometry increment
    (``config.odometry_linearisation = "iterated"``) kept its last iterate unconverged."""
    ambiguous_skipped: int = 0
    """Measurements left out, neither paired nor a feature of their own, because they
    fitted two features that cannot be one
    (:attr:`~mapfuse_core.matching.AssociationConfig.ambiguity` ``"skip"``; their
    ``obs_local_track`` is −1)."""
    obs_local_track: np.ndarray | None = None
    """(M,) int64 the feature each observation was given in its local map (a track id,
    −1 for none), before the joins merged it with global ones; the result's
    ``decisions.obs_landmark`` is the landmark the joins made of it.  A wrong pairing
    is the measurement association's when the observation disagrees with its local
    track, a join's when the local track went to another feature's landmark."""
