"""What the observations alone say about each landmark: :func:`landmark_evidence`.

A fused estimator merges a landmark paired with a known feature into that feature,
so its map holds the fused value, which cannot be tested against the known one.
The evidence is therefore re-estimated from the landmark's observations alone,
given the estimated trajectory: every observation ``z_j`` (sensor frame, step
``s_j``) is put in ``Wknown`` through the estimated pose and the anchor,
``f_j = x^Wknown_Wglobal ⊕ x^Wglobal_R(s_j) ⊕ z_j``, and the ``f_j`` are fused in the
residual coordinates of a reference feature (:mod:`mapfuse_core.changes.residual`).

Covariance: the measurement part is fused as independent (information sum); the
pose part is averaged, not divided by the count, because the pose errors of nearby
steps are almost fully correlated.  The pose covariance is the track's (in
``Wglobal``), an upper bound of the vehicle's uncertainty relative to the known map
when the map is fused; the anchor's own covariance is left out there because the
track's already carries it.  A filter's poses from before its map match do not: for
those steps the anchor's covariance is added (:func:`poses_in_known`).  The
trajectory has itself been corrected with the known feature under test, which pulls
the evidence towards it: the test is conservative (``docs/change-detection.md``).  When the
observations scatter about their fused value more than their measurement noise
allows, the fused covariance is scaled up by the excess (:func:`spread_factor`), so
that an inconsistent set cannot make a move on its own.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mapfuse_core.changes.residual import feature_residual
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import FloatArray, compose_jacobians
from mapfuse_core.measlog import MeasurementLog

__all__ = [
    "LandmarkEvidence",
    "ObservationSet",
    "fuse_against",
    "observation_sets",
    "observation_sets_in_known",
    "poses_in_known",
    "spread_factor",
]


@dataclass(frozen=True, eq=False)
class ObservationSet:
    """One landmark's observations, each in ``Wknown`` with its covariance parts."""

    landmark: int
    """Landmark (track) id of the decisions."""
    known_id: int
    """Known-map id the landmark is merged with, −1 if none."""
    kind: FeatureKind
    """Feature kind."""
    features: FloatArray
    """(n, 3) every observation in ``Wknown``."""
    meas_covs: FloatArray
    """(n, 3, 3) their covariance from the measurement noise."""
    pose_covs: FloatArray
    """(n, 3, 3) their covariance from the pose uncertainty."""
    extents: FloatArray
    """(n, 2) along-line extents of the observed segments (NaN for circles)."""
    steps: np.ndarray
    """(n,) steps of the observations."""
    true_id: int
    """Most frequent world id among the observations (−1 if none is known)."""
    estimate: tuple[FloatArray, FloatArray] | None = None
    """The estimator's own final estimate of this landmark in ``Wknown`` and its
    covariance (the anchor's uncertainty included jointly), used as the evidence
    instead of the observations when given (:func:`fuse_against`)."""

    @property
    def n_obs(self) -> int:
        """Number of observations."""
        return int(self.steps.shape[0])


@dataclass(frozen=True, eq=False)
class LandmarkEvidence:
    """Observation-only estimate of a landmark relative to a reference feature."""

    residual: FloatArray
    """(d,) fused residual of the observations from the reference (lines: lateral
    offset at the reference point (m), angle (rad); circles: dx, dy, dr (m))."""
    cov: FloatArray
    """(d, d) its covariance (measurement and pose parts, not the reference's)."""
    n_obs: int
    """Observations fused."""
    spread_factor: float = 1.0
    """Factor the measurement part of :attr:`cov` was multiplied by because the
    observations scatter more than their noise allows (:func:`spread_factor`)."""


def poses_in_known(
    x_Wknown_Wglobal: FloatArray,
    poses: FloatArray,
    pose_covs: FloatArray,
    anchor_cov: FloatArray | None = None,
    anchored_from_step: int = 0,
) -> tuple[FloatArray, FloatArray]:
    """A run's poses ``x^Wglobal_R`` put in ``Wknown`` through its anchor, with their
    covariances (NaN where the pose's is).

    ``anchor_cov``: the anchor's covariance, added through the composition's Jacobian
    to the poses before ``anchored_from_step``.  A filter's pose at such a step was
    estimated before the map was matched: its covariance says how well the pose is
    known in ``Wglobal``, not how well ``Wglobal`` is placed in ``Wknown``.  From the
    match on, the filter's track carries that through the known features.
    """
    PA = None if anchor_cov is None else np.asarray(anchor_cov, dtype=float)
    if PA is not None and (PA.shape != (3, 3) or not np.all(np.isfinite(PA))):
        raise ValueError(f"the anchor's covariance must be a finite 3×3 matrix, got {PA!r}")
    P = np.asarray(poses, dtype=float).reshape(-1, 3)
    C = np.asarray(pose_covs, dtype=float)
    out = np.zeros_like(P)
    covs = np.zeros((P.shape[0], 3, 3))
    for k in range(P.shape[0]):
        out[k], Ja, Jx = compose_jacobians(x_Wknown_Wglobal, P[k])
        covs[k] = Jx @ C[k] @ Jx.T
        if PA is not None and k < anchored_from_step:
            covs[k] += Ja @ PA @ Ja.T
    return out, covs


def observation_sets(
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses: FloatArray,
    pose_covs: FloatArray,
    x_Wknown_Wglobal: FloatArray,
    anchor_cov: FloatArray | None = None,
    anchored_from_step: int = 0,
) -> list[ObservationSet]:
    """Group the logged observations by landmark and put each in ``Wknown``.

    ``poses``/``pose_covs`` are the estimated ``x^Wglobal_R`` per step (a step beyond
    them, or with a non-finite pose, contributes nothing); ``anchor_cov`` and
    ``anchored_from_step`` as in :func:`poses_in_known`.
    """
    poses_K, covs_K = poses_in_known(
        x_Wknown_Wglobal, poses, pose_covs, anchor_cov, anchored_from_step
    )
    return observation_sets_in_known(log, obs_landmark, obs_known_id, poses_K, covs_K)


def observation_sets_in_known(
    log: MeasurementLog,
    obs_landmark: np.ndarray,
    obs_known_id: np.ndarray,
    poses_known: FloatArray,
    pose_covs_known: FloatArray,
) -> list[ObservationSet]:
    """:func:`observation_sets` from poses already in ``Wknown``
    (:func:`poses_in_known`); a non-finite pose covariance counts as zero."""
    lm = np.asarray(obs_landmark, dtype=np.int64)
    kn = np.asarray(obs_known_id, dtype=np.int64)
    if lm.shape != (log.n_features,) or kn.shape != lm.shape:
        raise ValueError(f"the decisions hold {lm.shape[0]} observations, the log {log.n_features}")
    poses = np.asarray(poses_known, dtype=float)
    n = poses.shape[0]
    covs = np.nan_to_num(np.asarray(pose_covs_known, dtype=float), nan=0.0)
    out = []
    for t in np.unique(lm[lm >= 0]).tolist():
        idx = np.nonzero(lm == t)[0]
        idx = idx[log.feat_step[idx] < n]
        idx = idx[np.all(np.isfinite(poses[log.feat_step[idx]]), axis=1)]
        if idx.size == 0:
            continue
        kinds = log.feat_kind[idx]
        kind = FeatureKind(int(np.bincount(kinds).argmax()))
        idx = idx[kinds == int(kind)]
        feats = np.zeros((idx.size, 3))
        mc = np.zeros((idx.size, 3, 3))
        pc = np.zeros((idx.size, 3, 3))
        for r, j in enumerate(idx.tolist()):
            s = int(log.feat_step[j])
            feats[r], Jx, Jz = transform_feature(kind, poses[s], log.feat_params[j])
            mc[r] = Jz @ log.feat_cov[j] @ Jz.T
            pc[r] = Jx @ covs[s] @ Jx.T
        tids = log.feat_true_id[idx]
        tids = tids[tids >= 0]
        out.append(
            ObservationSet(
                landmark=int(t),
                known_id=int(np.bincount(kn[idx] + 1).argmax()) - 1,
                kind=kind,
                features=feats,
                meas_covs=mc,
                pose_covs=pc,
                extents=np.asarray(log.feat_extent[idx], dtype=float),
                steps=np.asarray(log.feat_step[idx], dtype=np.int64),
                true_id=int(np.bincount(tids).argmax()) if tids.size else -1,
            )
        )
    return out


def fuse_against(obs: ObservationSet, reference: FloatArray) -> LandmarkEvidence:
    """Fuse ``obs`` in the residual coordinates of ``reference`` (same kind, ``Wknown``).

    With :attr:`ObservationSet.estimate` the evidence is that estimate instead: a
    filter's final estimate of a landmark it kept apart from the known map was
    corrected, through its correlations, by everything the filter saw after, the map
    match included, where the observations can only be read through the poses the
    filter had when it made them.  Its covariance is scaled by the observations' own
    spread factor: the estimate fused those observations trusting their noise, and
    when they scatter beyond it (a drifting, inconsistent run) so does the estimate.
    """
    res = []
    weights = []
    pose_part = None
    for f, C, D in zip(obs.features, obs.meas_covs, obs.pose_covs, strict=True):
        r, _, Jf = feature_residual(obs.kind, reference, f)
        res.append(r)
        weights.append(np.linalg.pinv(Jf @ C @ Jf.T, hermitian=True))
        Dp = Jf @ D @ Jf.T
        pose_part = Dp if pose_part is None else pose_part + Dp
    assert pose_part is not None
    info = np.sum(weights, axis=0)
    vec = np.sum([W @ r for W, r in zip(weights, res, strict=True)], axis=0)
    P = np.linalg.pinv(info, hermitian=True)
    est = P @ vec
    scale = spread_factor(res, weights, est)
    if obs.estimate is not None:
        value, Ce = obs.estimate
        est, _, Jf = feature_residual(obs.kind, reference, np.asarray(value, dtype=float))
        cov = scale * (Jf @ np.asarray(Ce, dtype=float) @ Jf.T)
    else:
        cov = scale * P + pose_part / obs.n_obs
    return LandmarkEvidence(
        residual=est, cov=0.5 * (cov + cov.T), n_obs=obs.n_obs, spread_factor=scale
    )


def spread_factor(res: list[FloatArray], weights: list[FloatArray], est: FloatArray) -> float:
    """How much more the observations scatter about their fused value than their
    measurement covariances allow: ``max(1, χ²/dof)`` with
    ``χ² = Σ (r_j − r̂)ᵀ W_j (r_j − r̂)`` over ``d·(n − 1)`` degrees of freedom (1 for a
    single observation).

    The fused covariance is multiplied by it.  Observations that disagree with each
    other beyond their noise (placed through poses that jump where the filter
    anchors, or a fit whose centre and radius are correlated near ±1 and biased) make
    the information-weighted mean unreliable, and can put it outside every observation;
    a statistic built on the unscaled covariance would then call a feature moved on
    the strength of that inconsistency alone."""
    n = len(res)
    if n < 2:
        return 1.0
    chi2 = sum(float((r - est) @ W @ (r - est)) for r, W in zip(res, weights, strict=True))
    dof = est.shape[0] * (n - 1)
    return float(max(1.0, chi2 / dof))
