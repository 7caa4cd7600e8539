"""The observation-only evidence of a landmark: the spread factor that keeps an
internally inconsistent set of observations from deciding a move on its own, and the
anchor's covariance on a filter's observations from before its map match."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.changes.evidence import (
    ObservationSet,
    fuse_against,
    observation_sets,
)
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from mapfuse_core.geometry.se2 import compose, relative
from tests.synthetic import synthetic_log

REF = np.array([10.0, 5.0, 0.6])


def _arc_cov(bearing: float, sigma: float = 0.05, rho: float = 0.98) -> np.ndarray:
    """Covariance of a circle fitted to a short arc seen along ``bearing``: the centre
    along the line of sight and the radius move together (correlation ``rho``)."""
    c, s = math.cos(bearing), math.sin(bearing)
    # (along, across, r) with along and r correlated, then rotated into (x, y, r).
    local = np.array([[1.0, 0.0, rho], [0.0, 0.3, 0.0], [rho, 0.0, 1.0]]) * sigma**2
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return R @ local @ R.T


def _set(shift_second_half: float, seed: int) -> ObservationSet:
    """30 observations of a tree at ``REF`` seen from bearings 0.6–1.4 rad, drawn from
    their covariances; the second half displaced by ``shift_second_half`` m along x
    (poses that jump where a filter anchors)."""
    rng = np.random.default_rng(seed)
    n = 30
    covs = np.array([_arc_cov(b) for b in np.linspace(0.6, 1.4, n)])
    feats = np.array([rng.multivariate_normal(REF, C) for C in covs])
    feats[n // 2 :, 0] += shift_second_half
    return ObservationSet(
        landmark=0,
        known_id=-1,
        kind=FeatureKind.CIRCLE,
        features=feats,
        meas_covs=covs,
        pose_covs=np.zeros((n, 3, 3)),
        extents=np.full((n, 2), np.nan),
        steps=np.arange(n),
        true_id=-1,
    )


def test_consistent_observations_keep_their_covariance():
    """Observations drawn from their own covariances: the factor stays below the
    0.999 quantile of χ²/dof (87 dof), and the fused residual is within 4 σ of 0."""
    bound = chi2.ppf(0.999, 87) / 87
    for seed in range(5):
        ev = fuse_against(_set(0.0, seed), REF)
        assert 1.0 <= ev.spread_factor < bound
        z = ev.residual / np.sqrt(np.diag(ev.cov))
        assert np.all(np.abs(z) < 4.0)


def test_a_jump_between_observations_scales_the_covariance_instead_of_making_a_move():
    """Half the observations 1 m along x off the other half, with centre and radius
    correlated at 0.98.  Their plain mean is off in x only; the information-weighted
    mean is also off in y and in radius, where no observation is.  Against the true
    place with the map's σ of 0.1 m, as the classifier tests it, the unscaled
    covariance fails the χ² test at 0.999; scaled by the spread factor, it passes."""
    obs = _set(1.0, seed=1)
    ev = fuse_against(obs, REF)
    assert ev.spread_factor > 100.0
    assert abs(obs.features[:, 1].mean() - REF[1]) < 0.05
    assert abs(obs.features[:, 2].mean() - REF[2]) < 0.05
    assert abs(ev.residual[1]) > 0.2
    assert abs(ev.residual[2]) > 0.2
    known = np.eye(3) * 0.1**2
    unscaled = ev.cov / ev.spread_factor + known  # no pose part here
    scaled = ev.cov + known
    threshold = chi2.ppf(0.999, 3)
    assert float(ev.residual @ np.linalg.solve(unscaled, ev.residual)) > threshold
    assert float(ev.residual @ np.linalg.solve(scaled, ev.residual)) < threshold


def test_a_single_observation_has_no_spread():
    obs = _set(0.0, seed=2)
    one = ObservationSet(
        landmark=0,
        known_id=-1,
        kind=FeatureKind.CIRCLE,
        features=obs.features[:1],
        meas_covs=obs.meas_covs[:1],
        pose_covs=obs.pose_covs[:1],
        extents=obs.extents[:1],
        steps=obs.steps[:1],
        true_id=-1,
    )
    ev = fuse_against(one, REF)
    assert ev.spread_factor == 1.0
    np.testing.assert_allclose(ev.residual, obs.features[0] - REF, atol=1e-12)


def test_observations_before_the_match_carry_the_anchors_covariance():
    """A filtered track's observations made before ``anchored_from_step`` get the
    anchor's covariance through the composition's Jacobian (checked against central
    differences of the observation put in ``Wknown``); those made from it on do not."""
    log = synthetic_log(steps=120, seed=3, known_fraction=0.7)
    start = log.true_poses[0]
    poses = np.array([relative(start, p)[0] for p in log.true_poses])
    covs = np.tile(np.eye(3) * 1e-6, (poses.shape[0], 1, 1))
    lm = log.feat_true_id.copy()
    kn = np.full_like(lm, -1)
    PA = np.diag([0.3**2, 0.2**2, 0.02**2])
    split = 60
    plain = observation_sets(log, lm, kn, poses, covs, start)
    with_anchor = observation_sets(
        log, lm, kn, poses, covs, start, anchor_cov=PA, anchored_from_step=split
    )
    checked_before = checked_after = 0
    for a, b in zip(plain, with_anchor, strict=True):
        idx = np.flatnonzero(lm == a.landmark)
        for r, j in enumerate(idx.tolist()):
            extra = b.pose_covs[r] - a.pose_covs[r]
            if a.steps[r] >= split:
                np.testing.assert_allclose(extra, 0.0, atol=1e-15)
                checked_after += 1
                continue

            def put(anchor: np.ndarray, j: int = j, kind: FeatureKind = a.kind) -> np.ndarray:
                x_K = compose(anchor, poses[int(log.feat_step[j])])
                return transform_feature(kind, x_K, log.feat_params[j])[0]

            J = np.zeros((3, 3))
            for i in range(3):
                h = np.zeros(3)
                h[i] = 1e-6
                J[:, i] = (put(start + h) - put(start - h)) / 2e-6
            np.testing.assert_allclose(extra, J @ PA @ J.T, atol=1e-8)
            checked_before += 1
    assert checked_before > 20
    assert checked_after > 20


def test_anchor_covariance_must_be_a_finite_3x3_matrix():
    log = synthetic_log(steps=20, seed=3, known_fraction=0.7)
    poses = np.zeros((20, 3))
    covs = np.zeros((20, 3, 3))
    with pytest.raises(ValueError, match="anchor's covariance"):
        observation_sets(
            log,
            log.feat_true_id,
            np.full_like(log.feat_true_id, -1),
            poses,
            covs,
            np.zeros(3),
            anchor_cov=np.full((3, 3), np.nan),
        )


def test_an_estimators_own_estimate_replaces_the_observations_as_evidence():
    """A set carrying the estimator's final estimate is tested through it: the residual
    is the estimate less the reference, whatever the observations say, and the
    covariance its own times the observations' spread factor: 1 for observations
    drawn from their noise, far more for a set with a 1 m jump, whose scatter the
    estimate (fused from the same observations) inherits."""
    C = np.diag([0.01, 0.02, 0.003])
    value = REF + np.array([0.3, -0.2, 0.05])
    calm = _set(0.0, seed=1)
    ev = fuse_against(dataclasses.replace(calm, estimate=(value, C)), REF)
    np.testing.assert_allclose(ev.residual, [0.3, -0.2, 0.05], atol=1e-12)
    plain = fuse_against(calm, REF)
    assert ev.spread_factor == plain.spread_factor
    np.testing.assert_allclose(ev.cov, plain.spread_factor * C, atol=1e-15)
    assert ev.n_obs == calm.n_obs
    jump = fuse_against(dataclasses.replace(_set(1.0, seed=1), estimate=(value, C)), REF)
    assert jump.spread_factor > 100.0
    np.testing.assert_allclose(jump.cov, jump.spread_factor * C, rtol=1e-12)
