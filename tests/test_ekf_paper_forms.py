"""The paper's three forms, each a setting of ``EKFConfig``: how the anchor enters
(``anchor_entry``, eqs. 12–16), how the known map reaches the local maps
(``known_map_in_local_maps``, eqs. 14, 17–24) and where a tie of two lines measures its
lateral residual (``line_tie_residual_at``, eqs. 5 and 20)."""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest
from scipy.stats import chi2

import ekf_reference.association as association
import ekf_reference.pipeline as pipeline
from ekf_reference import EKFConfig, run_ekf
from ekf_reference.anchoring import insert_ccda_estimate
from ekf_reference.association import Query, evaluate
from ekf_reference.known_frame import centred_known_map, uncentred
from ekf_reference.maps import copied_local_map, predict
from ekf_reference.pipeline import _Run, anchor_pose
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.evaluation import anchor_truth, nees_series, pose_errors
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import compose, inverse_jacobian
from mapfuse_core.matching.ccda import CCDAResult
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate

# --------------------------------------------------------------------------- helpers

KNOWN_VAR = 0.1**2
"""Variance of the one known circle's centre coordinates (still vehicle)."""
OBS_VAR = 1e-8
"""Variance of its observations: next to nothing, so the anchor is what the known map
and the anchor's own prior make it."""


def _still_log(steps: int = 80, seen: bool = True) -> MeasurementLog:
    """A vehicle standing at ``x^Wknown_R = (−5, 0, 0)``; one known circle (id 7) at the
    known frame's origin, σ 0.1 m; seen at ``(5, 0)`` at every step (``seen``) with σ
    1e-4 m, or never."""
    rng = np.random.default_rng(3)
    m = steps if seen else 0
    z = np.array([5.0, 0.0, 0.3]) + rng.normal(0.0, math.sqrt(OBS_VAR), (m, 3))
    known = KnownMapArrays(
        ids=np.array([7], dtype=np.int64),
        kinds=np.array([int(FeatureKind.CIRCLE)], dtype=np.int8),
        params=np.array([[0.0, 0.0, 0.3]]),
        covs=np.array([KNOWN_VAR * np.eye(3)]),
        extents=np.full((1, 2), np.nan),
    )
    return MeasurementLog(
        scenario="still",
        seed=3,
        timestamps=np.arange(steps) * 0.125,
        odometry=np.zeros((steps, 3)),
        odometry_cov=np.tile(1e-12 * np.eye(3), (steps, 1, 1)),
        feat_step=np.arange(m, dtype=np.int64),
        feat_kind=np.full(m, int(FeatureKind.CIRCLE), dtype=np.int8),
        feat_params=z.reshape(m, 3),
        feat_cov=np.tile(OBS_VAR * np.eye(3), (m, 1, 1)),
        feat_true_id=np.full(m, 7, dtype=np.int64),
        feat_n_points=np.full(m, 10, dtype=np.int64),
        feat_extent=np.full((m, 2), np.nan),
        known_map=known,
        true_poses=np.tile([-5.0, 0.0, 0.0], (steps, 1)),
    )


def _ccda(x: np.ndarray, cov: np.ndarray) -> CCDAResult:
    """An accepted CCDA result without pairings: transform ``x`` with covariance ``cov``."""
    return CCDAResult(
        True, "accepted", (), np.asarray(x, float), np.asarray(cov, float), 0, 0, 0, 0
    )


def _anchor_var_after_two_joins(mode: str, seen: bool, P: np.ndarray) -> np.ndarray:
    """Diagonal of the global anchor's covariance after the joins at steps 39 and 79 of
    :func:`_still_log`, the map matched before step 0 with ``x^Wglobal_Wknown = (5, 0,
    0)`` and covariance ``P`` (entered as CCDA's estimate), the known map ``mode``."""
    log = _still_log(seen=seen)
    config = dataclasses.replace(
        EKFConfig.paper(), known_map_in_local_maps=mode, line_tie_residual_at="observed"
    )
    run = _Run(log, config)
    res = _ccda([5.0, 0.0, 0.0], P)
    trial, index = insert_ccda_estimate(
        run.global_map, res, run.known if mode == "shared" else None
    )
    run._fuse_match(0, [], res, trial, index, None)
    run.local, run.ctx = run._start_local_map([])
    for k in range(log.n_steps):
        if k > 0:
            predict(run.local, log.odometry[k], log.odometry_cov[k])
        run.observe(k)
        if (k + 1) % config.local_map_steps == 0:
            run.join(k)
    g = run.global_map
    return np.diag(g.block(g.find(Role.ANCHOR))).copy()


@functools.cache
def _loop600(steps: int) -> MeasurementLog:
    """loop600, seed 0, its first ``steps`` steps (the first match is at the first join)."""
    sc = dataclasses.replace(load_scenario("loop600"), steps=steps)
    return simulate(sc, seed=0, workers=1).log


# --------------------------------------------------------------------------- settings


def test_the_forms_are_literal_choices() -> None:
    for name in ("anchor_entry", "known_map_in_local_maps", "line_tie_residual_at"):
        with pytest.raises(ValueError, match=f"{name} must be one of"):
            EKFConfig(**{name: "paper"})  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="carry_seen_steps shares features"):
        EKFConfig(known_map_in_local_maps="copied", carry_seen_steps=1)


# --------------------------------------------------------------------------- anchor entry


def test_ccda_estimate_enters_with_ccdas_estimate_and_covariance() -> None:
    """Eqs. 13–16 with a map whose base is uncertain and correlated with its features:
    the anchor's ``x^Wknown_Wglobal`` is CCDA's ``⊖x^Wglobal_Wknown`` with CCDA's
    covariance, and the anchor is correlated with the map through the base only."""
    rng = np.random.default_rng(5)
    g = GaussianMap()
    g.elements = [
        Element(ElementKind.POSE, Role.BASE, moving=False, track=-1),
        Element(ElementKind.CIRCLE, Role.FEATURE, moving=False, track=0),
        Element(ElementKind.CIRCLE, Role.FEATURE, moving=False, track=1),
    ]
    g.mean = np.array([[-12.0, 4.0, 2.1], [3.0, 1.0, 0.4], [-6.0, 8.0, 0.3]])
    A = rng.normal(0.0, 0.2, (9, 9))
    g.cov = A @ A.T + 1e-3 * np.eye(9)
    x = np.array([20.0, -7.0, 0.8])
    C = np.array([[4e-4, 1e-4, 2e-6], [1e-4, 9e-4, -3e-6], [2e-6, -3e-6, 1e-6]])
    trial, index = insert_ccda_estimate(g, _ccda(x, C), None)
    assert index == {}
    est, cov = anchor_pose(trial)
    inv, J = inverse_jacobian(x)
    np.testing.assert_allclose(est, inv, atol=1e-12)
    np.testing.assert_allclose(cov, J @ C @ J.T, atol=1e-15)
    # x^Wlocal_Wknown = x^Wlocal_Wglobal ⊕ x^Wglobal_Wknown (eq. 13).
    a = trial.find(Role.ANCHOR)
    np.testing.assert_allclose(trial.mean[a], compose(g.mean[0], x), atol=1e-12)
    # The map is as it was.
    np.testing.assert_array_equal(trial.cov[:9, :9], g.cov)


def test_paper_run_anchors_where_ccda_put_it(monkeypatch: pytest.MonkeyPatch) -> None:
    """loop600's first 40 steps with the paper's preset: the match at the join of step
    39 is the run's last event, so the run's anchor is CCDA's estimate of the map in
    ``Wglobal`` and its covariance, as inserted."""
    log = _loop600(40)
    seen: list[CCDAResult] = []

    def recording(*args: object, **kwargs: object) -> CCDAResult:
        res = ccda_match(*args, **kwargs)
        seen.append(res)
        return res

    ccda_match = pipeline.ccda_match
    monkeypatch.setattr(pipeline, "ccda_match", recording)
    res = run_ekf(log, EKFConfig.paper())
    assert res.anchor is not None
    assert res.anchor.accepted_at_step == 39
    ccda = seen[-1]
    assert ccda.accepted
    inv, J = inverse_jacobian(ccda.x_A_B)
    centre = centred_known_map(log.known_map)[1]
    np.testing.assert_allclose(res.anchor.x_Wknown_Wglobal, uncentred(inv, centre), atol=1e-9)
    np.testing.assert_allclose(res.anchor.cov, J @ ccda.cov @ J.T, rtol=1e-9, atol=1e-15)
    # CCDA matched the map in Wglobal: its transform is x^Wglobal_Wknown, within a few
    # of its σ (a few cm) of the truth; in Wlocal it would be 10 m off.
    assert log.true_poses is not None
    err = pose_errors(res.anchor.x_Wknown_Wglobal[None], anchor_truth(log.true_poses)[None])
    assert float(nees_series(err.dx, res.anchor.cov[None])[0]) < chi2.ppf(0.999, 3)


# --------------------------------------------------------------------------- known map


def test_copied_local_map_holds_independent_copies() -> None:
    """Eqs. 17–19: the anchor at its global value and marginal covariance, the known
    features with their surveyed covariance, nothing correlated."""
    log = _still_log()
    known = centred_known_map(log.known_map)[0]
    g = GaussianMap()
    g.elements = [
        Element(ElementKind.POSE, Role.BASE, moving=False, track=-1),
        Element(ElementKind.POSE, Role.ANCHOR, moving=False, track=-1),
    ]
    g.mean = np.array([[1.0, 2.0, 0.3], [5.0, 0.0, 0.1]])
    g.cov = np.full((6, 6), 1e-3) + np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0]) * 1e-2
    loc = copied_local_map(g, known, {0: 11})
    assert [(e.role, e.moving) for e in loc.elements] == [
        (Role.BASE, True),
        (Role.ANCHOR, True),
        (Role.KNOWN, False),
    ]
    assert loc.elements[2].track == 11
    np.testing.assert_array_equal(loc.mean, [[0.0, 0.0, 0.0], [5.0, 0.0, 0.1], [0.0, 0.0, 0.3]])
    expected = np.zeros((9, 9))
    expected[3:6, 3:6] = g.cov[3:6, 3:6]
    expected[6:, 6:] = KNOWN_VAR * np.eye(3)
    np.testing.assert_array_equal(loc.cov, expected)


@pytest.mark.parametrize("mode", ["shared", "copied"])
def test_an_unobserved_anchor_after_two_joins(mode: str) -> None:
    """Nothing observed and no motion: shared, the anchor keeps its covariance ``P``;
    copied, each join ties the global anchor to a copy of itself taken as independent,
    so its covariance halves at every join: ``P/4`` after two."""
    P = np.diag([0.04, 0.09, 0.01])
    var = _anchor_var_after_two_joins(mode, seen=False, P=P)
    np.testing.assert_allclose(var, np.diag(P) / (1.0 if mode == "shared" else 4.0), rtol=1e-6)


@pytest.mark.parametrize("mode", ["shared", "copied"])
def test_a_known_feature_counted_at_every_join(mode: str) -> None:
    """One known circle at the known frame's origin (variance ``C``), seen from a still
    vehicle with next to no noise, an anchor of prior variance ``P`` in x and y and a
    known heading (the circle cannot tell it, and the EKF would otherwise learn it
    from the changing linearisation points of near-exact observations).

    Shared, the circle's information enters once: ``1/(1/P + 1/C)``.  Copied (in
    information): the first local map's anchor has ``1/P + 1/C`` (its copy and the
    circle's), and the join adds the global anchor's ``1/P``; the second local map's
    copy has ``2/P + 1/C``, its own copy of the circle ``1/C``, and the join adds the
    global ``2/P + 1/C`` again (its observed circle pairs with the first one, both
    exactly placed relative to the vehicle, which adds nothing): ``4/P + 3/C``.
    """
    P = np.diag([1.0, 1.0, 1e-12])
    var = _anchor_var_after_two_joins(mode, seen=True, P=P)
    p, c = P[0, 0], KNOWN_VAR
    want = 1.0 / (1 / p + 1 / c) if mode == "shared" else 1.0 / (4 / p + 3 / c)
    np.testing.assert_allclose(var[:2], want, rtol=1e-3)


def test_every_combination_runs_with_the_extensions() -> None:
    """The default's extensions (the anchor watch, the known-map gate, the match tests)
    with each paper's form: each fuses loop600's first match."""
    log = _loop600(200)
    for change in (
        {"anchor_entry": "ccda_estimate"},
        {"known_map_in_local_maps": "copied"},
        {"line_tie_residual_at": "target"},
    ):
        res = run_ekf(log, dataclasses.replace(EKFConfig(), **change))  # type: ignore[arg-type]
        assert res.anchor is not None, change
        assert res.anchor.accepted_at_step == 39, change
        assert res.map.known_ids.max() >= 0, change


# --------------------------------------------------------------------------- line ties


def _wall_tie(at: str, delta: float) -> tuple[np.ndarray, np.ndarray]:
    """``∂r/∂x^R_Wknown`` of the tie of a local line to a known wall it makes an angle
    ``delta`` with, the local line's reference point 15 m along the wall from the
    wall's; and the wall's direction in ``R``."""
    m = GaussianMap()
    m.elements = [
        Element(ElementKind.POSE, Role.BASE, moving=True, track=-1),
        Element(ElementKind.POSE, Role.ANCHOR, moving=True, track=-1),
        Element(ElementKind.LINE, Role.KNOWN, moving=False, track=1),
        Element(ElementKind.LINE, Role.FEATURE, moving=True, track=2),
    ]
    anchor = np.array([4.0, -3.0, 0.5])
    wall = np.array([10.0, 2.0, 0.2])
    wall_r = compose(anchor, wall)
    feature = compose(wall_r, np.array([15.0, 0.0, delta]))
    m.mean = np.array([np.zeros(3), anchor, wall, feature])
    m.cov = 1e-2 * np.eye(12)
    c = evaluate(m, Query(ElementKind.LINE, feature, np.zeros((3, 3)), (0.0, 0.0), 3, at), 2)  # type: ignore[arg-type]
    assert c.indices == [3, 1, 2]
    return c.H[:, 3:6], np.array([math.cos(wall_r[2]), math.sin(wall_r[2]), 0.0])


@pytest.mark.parametrize("delta", [0.01, -0.03])
def test_a_tie_at_the_walls_reference_point_knows_the_anchor_along_the_wall(delta: float) -> None:
    """Moving the anchor along the wall moves the wall's reference point along itself:
    at the local line's point (observed) the lateral residual does not see it; at the
    wall's (target, eq. 20) it sees it through the angle between them, ``sin δ``."""
    H_obs, u = _wall_tie("observed", delta)
    H_tgt, _ = _wall_tie("target", delta)
    assert abs(float(H_obs[0] @ u)) < 1e-12
    assert float(H_tgt[0] @ u) == pytest.approx(math.sin(delta), abs=1e-12)


def test_a_measurement_is_measured_at_its_segment() -> None:
    m = GaussianMap()
    m.add(Element(ElementKind.LINE, Role.FEATURE, moving=True, track=0), np.zeros(3), np.eye(3))
    q = Query(ElementKind.LINE, np.zeros(3), np.eye(3), (0.0, 0.0), residual_at="target")
    with pytest.raises(ValueError, match="measured segment"):
        evaluate(m, q, 0)


@pytest.mark.parametrize("config", ["paper", "default"])
def test_ties_measure_where_the_setting_says(config: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """Every line residual of a measurement is taken at its segment; every tie (local
    lines with known walls and, at the joins, with global lines) where
    ``line_tie_residual_at`` says."""
    calls: dict[tuple[bool, str], int] = {}

    def counting_evaluate(state: GaussianMap, q: Query, t: int):  # type: ignore[no-untyped-def]
        if q.kind == ElementKind.LINE:
            key = (q.element >= 0, q.residual_at)
            calls[key] = calls.get(key, 0) + 1
        return evaluate(state, q, t)

    monkeypatch.setattr(association, "evaluate", counting_evaluate)
    monkeypatch.setattr(pipeline, "evaluate", counting_evaluate)
    cfg = EKFConfig.paper() if config == "paper" else EKFConfig()
    run_ekf(_loop600(120), cfg)
    tie = cfg.line_tie_residual_at
    assert set(calls) == {(False, "observed"), (True, tie)}
    assert calls[(True, tie)] > 0
