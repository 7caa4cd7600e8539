"""Re-placing a filter's poses before its match, on a drive with uneven odometry:
dead reckoning both ways, the step after the match as a source, the fusion with the
filtered pose, the gates, the χ² test's degrees of freedom and degenerate inputs."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.stats import chi2

from mapfuse_core.changes.relocalize import _place, _solve, _Tie, relocalize_before_match
from mapfuse_core.geometry.features import FeatureKind, express_in
from mapfuse_core.geometry.se2 import compose
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from tests.test_changes_relocalize import LEVEL, LOOSE, _err, _filtered

Q = np.diag([0.02**2, 0.01**2, 0.003**2])
"""Odometry covariance per step."""
TREES = np.array([[6.0, 3.0, 0.3], [4.0, -5.0, 0.4], [-3.0, 2.0, 0.2], [8.0, -1.0, 0.35]])
"""Known trees, given in the frame of the pose that sees them."""


def _drive(n: int, seen_at: list[int], seed: int = 0) -> MeasurementLog:
    """A drive of ``n`` steps with uneven increments (0.3–0.7 m, turns of up to
    0.15 rad) and odometry drawn from :data:`Q`; at each step of ``seen_at`` four
    exact trees are observed exactly, placed around that step's true pose."""
    rng = np.random.default_rng(seed)
    true = np.zeros((n, 3))
    odo = np.zeros((n, 3))
    for k in range(1, n):
        u = np.array([rng.uniform(0.3, 0.7), rng.normal(0.0, 0.05), rng.uniform(-0.15, 0.15)])
        true[k] = compose(true[k - 1], u)
        odo[k] = u + rng.multivariate_normal(np.zeros(3), Q)
    odo_cov = np.repeat(Q[None], n, axis=0)
    odo_cov[0] = 0.0
    ids, params, steps, z = [], [], [], []
    for s in seen_at:
        for t in TREES:
            w = np.array([*compose(true[s], np.array([t[0], t[1], 0.0]))[:2], t[2]])
            ids.append(len(ids) + 1)
            params.append(w)
            steps.append(s)
            z.append(express_in(FeatureKind.CIRCLE, true[s], w)[0])
    m = len(ids)
    known = KnownMapArrays(
        ids=np.array(ids, dtype=np.int64),
        kinds=np.full(m, int(FeatureKind.CIRCLE), dtype=np.int8),
        params=np.array(params, dtype=float).reshape(m, 3),
        covs=np.repeat(np.diag([1e-4, 1e-4, 1e-4])[None], m, axis=0),
        extents=None,
    )
    return MeasurementLog(
        scenario="drive",
        seed=seed,
        timestamps=np.arange(n) * 0.1,
        odometry=odo,
        odometry_cov=odo_cov,
        feat_step=np.array(steps, dtype=np.int64),
        feat_kind=np.full(m, int(FeatureKind.CIRCLE), dtype=np.int8),
        feat_params=np.array(z, dtype=float).reshape(m, 3),
        feat_cov=np.repeat(np.diag([1e-4, 1e-4, 1e-4])[None], m, axis=0),
        feat_true_id=known.ids.copy(),
        feat_n_points=np.full(m, 10, dtype=np.int64),
        feat_extent=np.full((m, 2), np.nan),
        known_map=known,
        world=known,
        true_poses=true,
    )


def _ids(log: MeasurementLog) -> np.ndarray:
    return log.feat_true_id.astype(np.int64)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_both_directions_of_dead_reckoning_follow_uneven_odometry_within_their_covariance(seed):
    """Placed at steps 0 and 60 only: the 59 steps between are dead-reckoned forwards
    from 0 or backwards from 60, through increments that differ at every step.  Every
    bridged pose is within four of its own σ per axis of the truth (one in 16,000 for
    a Gaussian, over some 180 values per seed), and so are the steps bridged
    backwards (31–59), which an increment read from the wrong row would put metres
    off."""
    log = _drive(61, [0, 60], seed)
    ids = _ids(log)
    poses, covs = _filtered(log)
    out = relocalize_before_match(log, ids, ids, poses, covs, 61, LEVEL)
    assert (out.relocalized, out.bridged) == (2, 59)
    assert log.true_poses is not None
    for k in range(61):
        e = _err(out.poses[k], log.true_poses[k])
        assert np.all(np.abs(e) <= 4.0 * np.sqrt(np.diag(out.covs[k]))), k


def test_the_steps_just_before_the_match_are_dead_reckoned_back_from_the_first_anchored_pose():
    """No step before the match sees a merged feature; the pose at the match step
    (the filter's, anchored) is the truth with σ 1 cm.  The 40 steps before it are
    dead-reckoned back from it, within four of their σ of the truth and far tighter
    than filtered; a run whose match step is beyond the poses bridges nothing."""
    log = _drive(41, [])
    ids = _ids(log)
    poses, covs = _filtered(log)
    assert log.true_poses is not None
    poses[40] = log.true_poses[40]
    covs[40] = np.diag([1e-4, 1e-4, 1e-6])
    out = relocalize_before_match(log, ids, ids, poses, covs, 40, LEVEL)
    assert (out.relocalized, out.bridged) == (0, 40)
    for k in range(40):
        e = _err(out.poses[k], log.true_poses[k])
        assert np.all(np.abs(e) <= 4.0 * np.sqrt(np.diag(out.covs[k])))
        assert np.trace(out.covs[k][:2, :2]) < 0.05 * np.trace(LOOSE[:2, :2])
    np.testing.assert_array_equal(out.poses[40], poses[40])
    none = relocalize_before_match(log, ids, ids, poses, covs, 41, LEVEL)
    assert (none.relocalized, none.bridged) == (0, 0)
    np.testing.assert_array_equal(none.poses, poses)


def test_a_placement_is_fused_with_the_filtered_pose_by_their_information():
    """With the filtered pose as prior the result is the information-weighted mean of
    it and the placement alone (a non-finite prior): ``P = (P0⁻¹ + Pr⁻¹)⁻¹`` and
    ``x = P (P0⁻¹ x0 + Pr⁻¹ xr)``, to 1e-9 (the poses are 0.1 rad apart at most, so
    the linear fusion holds to rounding)."""
    log = _drive(1, [0])
    ids = _ids(log)
    loose = np.diag([0.003**2, 0.002**2, 0.0005**2])
    x0 = np.array([[0.004, -0.002, 0.0007]])
    alone = relocalize_before_match(log, ids, ids, x0, np.full((1, 3, 3), np.nan), 1, LEVEL)
    fused = relocalize_before_match(log, ids, ids, x0, loose[None], 1, LEVEL)
    xr, Pr = alone.poses[0], alone.covs[0]
    W0, Wr = np.linalg.inv(loose), np.linalg.inv(Pr)
    P = np.linalg.inv(W0 + Wr)
    np.testing.assert_allclose(fused.covs[0], P, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(fused.poses[0], P @ (W0 @ x0[0] + Wr @ xr), atol=1e-9)
    assert np.trace(fused.covs[0]) < min(np.trace(loose), np.trace(Pr))


def test_a_bridge_that_disagrees_with_the_filtered_pose_is_not_taken():
    """Step 0 is placed (its filtered covariance non-finite, so the placement stands
    alone); the later steps' filtered poses claim 5 cm while 1.8 m off: the bridge
    from step 0 is tighter but disagrees with them beyond the gate, so they keep
    their filtered poses."""
    log = _drive(11, [0])
    ids = _ids(log)
    poses, _ = _filtered(log)
    covs = np.repeat(np.diag([0.05**2, 0.05**2, 0.01**2])[None], 11, axis=0)
    covs[0] = np.nan
    out = relocalize_before_match(log, ids, ids, poses, covs, 11, LEVEL)
    assert (out.relocalized, out.bridged) == (1, 0)
    np.testing.assert_array_equal(out.poses[1:], poses[1:])


def _ties(shift: float) -> list[_Tie]:
    """The four trees of step 0 seen exactly from the origin, the first one's known
    entry shifted by ``shift`` m along x."""
    out = []
    for i, t in enumerate(TREES[:3]):
        known = t.copy()
        if i == 0:
            known[0] += shift
        out.append(
            _Tie(FeatureKind.CIRCLE, t.copy(), np.eye(3) * 1e-4, known, np.eye(3) * 1e-4, i + 1)
        )
    return out


def test_the_placement_test_has_two_per_tie_less_three_degrees_of_freedom():
    """Three trees, one shifted so that the placement's χ² falls between the 0.999
    quantiles of 3 and 6 degrees of freedom: with 2·3 − 3 = 3 the placement fails,
    and, two trees too few once the worst is set aside, is refused; a shift giving a
    χ² below the 3-dof quantile is accepted with all three."""
    one = _solve(_ties(0.1), np.zeros(3))
    assert one is not None
    per = sum(one[2]) / 0.1**2
    between = 0.5 * (chi2.ppf(LEVEL, 3) + chi2.ppf(LEVEL, 6))
    assert _place(_ties(float(np.sqrt(between / per))), np.zeros(3), LEVEL) is None
    below = 0.8 * chi2.ppf(LEVEL, 3)
    kept = _place(_ties(float(np.sqrt(below / per))), np.zeros(3), LEVEL)
    assert kept is not None
    assert len(kept[2]) == 3


def test_ties_without_a_positive_definite_covariance_are_left_out_not_a_traceback():
    """Known trees with zero covariance observed with zero noise: those ties cannot be
    weighed; with all four degenerate the step is not placed, with one degenerate the
    other three place it.  A known id absent from the map is no tie."""
    log = _drive(1, [0])
    ids = _ids(log)
    x0 = np.array([[0.3, -0.2, 0.02]])
    exact = dataclasses.replace(
        log,
        feat_cov=np.zeros_like(log.feat_cov),
        known_map=dataclasses.replace(log.known_map, covs=np.zeros_like(log.known_map.covs)),
    )
    out = relocalize_before_match(exact, ids, ids, x0, LOOSE[None], 1, LEVEL)
    assert (out.relocalized, out.refused) == (0, 0)
    covs = log.known_map.covs.copy()
    covs[0] = 0.0
    fcov = log.feat_cov.copy()
    fcov[0] = 0.0
    one = dataclasses.replace(
        log, feat_cov=fcov, known_map=dataclasses.replace(log.known_map, covs=covs)
    )
    out = relocalize_before_match(one, ids, ids, x0, LOOSE[None], 1, LEVEL)
    assert out.relocalized == 1
    assert np.linalg.norm(out.poses[0][:2]) < 0.01
    stray = np.where(ids == 1, 999, ids)
    out = relocalize_before_match(log, ids, stray, x0, LOOSE[None], 1, LEVEL)
    assert out.relocalized == 1


def test_more_poses_than_steps_and_a_match_step_beyond_them_are_handled():
    """Poses for 15 steps of a 10-step log, the match step past both: the steps of the
    log are handled, the extra poses are left as they are."""
    log = _drive(10, [0, 9])
    ids = _ids(log)
    poses, covs = _filtered(log)
    poses = np.vstack([poses, np.zeros((5, 3))])
    covs = np.concatenate([covs, np.repeat(LOOSE[None], 5, axis=0)])
    out = relocalize_before_match(log, ids, ids, poses, covs, 20, LEVEL)
    assert (out.relocalized, out.bridged) == (2, 8)
    np.testing.assert_array_equal(out.poses[10:], poses[10:])
    empty = relocalize_before_match(log, ids, ids, poses, covs, 0, LEVEL)
    assert (empty.relocalized, empty.bridged) == (0, 0)


def test_a_backward_step_carries_the_increments_covariance_through_its_inverse():
    """One step back from a pose known exactly, through an increment of (2, 1, 0.5)
    with σθ = 0.05 rad: the covariance of ``x1 ⊕ ⊖u`` (the heading's noise swings the
    position by the increment's length) matches that of 20,000 draws to 5 % of its
    norm (sampling error about 1 %, the linearisation's well below)."""
    from mapfuse_core.changes.relocalize import _sweep
    from mapfuse_core.geometry.se2 import inverse

    q = np.diag([0.05**2, 0.03**2, 0.05**2])
    u = np.array([2.0, 1.0, 0.5])
    x1 = np.array([3.0, -1.0, 2.0])
    log = dataclasses.replace(
        _drive(2, []), odometry=np.array([np.zeros(3), u]), odometry_cov=np.array([q * 0, q])
    )
    poses = np.array([np.zeros(3), x1])
    covs = np.zeros((2, 3, 3))
    got = _sweep(log, poses, covs, np.array([False, True]), range(1, -1, -1), forward=False)
    rng = np.random.default_rng(0)
    draws = np.array(
        [compose(x1, inverse(u + rng.multivariate_normal(np.zeros(3), q))) for _ in range(20000)]
    )
    x0, P = got[0]
    np.testing.assert_allclose(x0, compose(x1, inverse(u)), atol=1e-12)
    emp = np.cov(draws.T)
    assert np.linalg.norm(P - emp) < 0.05 * np.linalg.norm(emp)
