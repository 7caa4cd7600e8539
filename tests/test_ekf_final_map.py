"""The EKF's final map in ``Wknown``: each landmark kept apart from the known map, with
the covariance of its joint marginal with the anchor (``ekf_reference.final_map``)."""

from __future__ import annotations

import numpy as np

from ekf_reference import EKFConfig, run_ekf
from mapfuse.runner import run
from mapfuse_core.geometry.features import FeatureKind, transform_feature
from tests.synthetic import synthetic_log


def _run():
    log = synthetic_log(steps=300, seed=3, known_fraction=0.5)
    return log, run_ekf(log, EKFConfig(), fusion=True)


def test_landmarks_in_wknown_are_the_anchor_composed_with_their_wglobal_estimate():
    """The same means by two paths (``⊖x^Wlocal_Wknown ⊕ x^Wlocal_F`` and
    ``x^Wknown_Wglobal ⊕ x^Wglobal_F``) agree to 1e-9; known features, and landmarks
    without an anchor, carry NaN; every track id names the decisions' landmark."""
    log, res = _run()
    assert res.anchor is not None
    gm = res.map
    assert gm.params_known is not None
    assert gm.covs_known is not None
    assert gm.tracks is not None
    apart = gm.known_ids < 0
    assert apart.sum() >= 5
    for f in np.nonzero(apart)[0]:
        kind = FeatureKind(int(gm.kinds[f]))
        via, _, _ = transform_feature(kind, res.anchor.x_Wknown_Wglobal, gm.params[f])
        got = gm.params_known[f]
        if kind == FeatureKind.CIRCLE:
            np.testing.assert_allclose(got, via, atol=1e-9)
        else:
            # Lines: the same line (reference point and angle), up to the angle's 2π.
            np.testing.assert_allclose(got[:2], via[:2], atol=1e-9)
            assert abs(np.angle(np.exp(1j * (got[2] - via[2])))) < 1e-9
        assert np.all(np.linalg.eigvalsh(gm.covs_known[f]) > -1e-12)
    assert np.all(np.isnan(gm.params_known[~apart]))
    assert set(gm.tracks[apart].tolist()) <= set(res.decisions.obs_landmark.tolist())
    none = run_ekf(log, EKFConfig(), fusion=False).map
    assert none.params_known is not None
    assert np.all(np.isnan(none.params_known))


def test_landmarks_in_wknown_are_consistent_and_tighter_than_the_marginals_composed():
    """Against the truth, the circles kept apart have a mean 2-dof NEES below 6 (an
    EKF's; chance alone keeps it under 4 for some 14 landmarks), and their joint
    covariance is tighter than the anchor's and the landmark's marginals composed as if
    independent, which count the unanchored drift twice."""
    log, res = _run()
    assert res.anchor is not None
    assert log.world is not None
    gm = res.map
    assert gm.params_known is not None
    assert gm.covs_known is not None
    world = {int(i): p for i, p in zip(log.world.ids, log.world.params, strict=True)}
    nees, tighter, n = [], 0, 0
    for f in np.nonzero((gm.known_ids < 0) & (gm.kinds == int(FeatureKind.CIRCLE)))[0]:
        t = int(gm.true_ids[f])
        if t not in world:
            continue
        e = gm.params_known[f][:2] - world[t][:2]
        nees.append(float(e @ np.linalg.solve(gm.covs_known[f][:2, :2], e)))
        _, Ja, Jf = transform_feature(FeatureKind.CIRCLE, res.anchor.x_Wknown_Wglobal, gm.params[f])
        apart = Ja @ res.anchor.cov @ Ja.T + Jf @ gm.covs[f] @ Jf.T
        n += 1
        tighter += np.trace(gm.covs_known[f][:2, :2]) <= np.trace(apart[:2, :2]) + 1e-12
    assert n >= 5
    assert np.mean(nees) < 6.0
    assert tighter == n


def test_the_harness_result_carries_them():
    log, res = _run()
    m = run(log, "ekf").result.map
    assert m.tracks is not None
    np.testing.assert_array_equal(m.tracks, res.map.tracks)
    np.testing.assert_array_equal(m.params_known, res.map.params_known)
