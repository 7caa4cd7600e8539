"""The observation update through the step's odometry increment
(``EKFConfig.odometry_linearisation = "iterated"``, :mod:`ekf_reference.increment`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.optimize import least_squares

from ekf_reference import EKFConfig, increment, run_ekf
from ekf_reference.association import Query, apply, evaluate
from ekf_reference.increment import Increment, _chained, update_through_increment
from ekf_reference.maps import motion, predict
from ekf_reference.state import Element, ElementKind, GaussianMap, Role, bind_line_cov
from mapfuse_core.evaluation import nees_series, pose_errors, truth_in_global
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.models import observe
from tests.synthetic import ring_world, synthetic_log

U = np.array([0.4, 0.05, 0.08])
Q = np.diag([0.03, 0.01, 0.05]) ** 2
"""A rough increment: 0.05 rad of heading σ, as a laser log's scan-to-scan odometry."""


def _random_cov(rng: np.random.Generator, n: int, scale: float) -> np.ndarray:
    A = rng.normal(size=(n, n)) * scale
    return A @ A.T + 1e-6 * np.eye(n)


def local_map(rng: np.random.Generator, lines: bool = True) -> GaussianMap:
    """A local map before a step: base, three circles, (two lines), a static element,
    with a correlated covariance."""
    m = GaussianMap()
    m.add(Element(ElementKind.POSE, Role.BASE, True, -1), np.array([-3.0, 1.0, 0.2]), np.eye(3))
    for i, c in enumerate(([8.0, 2.0, 0.4], [5.0, -6.0, 0.3], [12.0, 7.0, 0.5])):
        m.add(Element(ElementKind.CIRCLE, Role.FEATURE, True, i), np.array(c), np.eye(3))
    if lines:
        for i, ln in enumerate(([6.0, 4.0, 0.3], [-2.0, -5.0, 1.9])):
            m.add(Element(ElementKind.LINE, Role.FEATURE, True, 10 + i), np.array(ln), np.eye(3))
    m.add(Element(ElementKind.POSE, Role.ANCHOR, False, -1), np.array([1.0, 2.0, 0.1]), np.eye(3))
    m.cov = _random_cov(rng, 3 * len(m), 0.05)
    m.bind_lines()
    return m


def test_without_pairings_the_update_is_the_prediction() -> None:
    before = local_map(np.random.default_rng(0))
    expected = before.copy()
    predict(expected, U, Q)
    got = before.copy()
    predict(got, U, Q)
    upd = update_through_increment(got, Increment(before.copy(), U, Q), lambda s: [])
    assert upd.iterations == 0
    np.testing.assert_allclose(got.mean, expected.mean, atol=1e-12)
    np.testing.assert_allclose(got.cov, expected.cov, atol=1e-12)


def _queries(m: GaussianMap, rng: np.random.Generator) -> list[tuple[Query, int]]:
    """Measurements of circles 1, 2 and line 4 (in ``R``), 2 cm and 0.01 rad σ."""
    out = []
    for t in (1, 2, 4):
        e = m.elements[t]
        z = m.mean[t] + rng.normal(scale=[0.02, 0.02, 0.01])
        if e.kind == ElementKind.CIRCLE:
            R = np.diag([0.02, 0.02, 0.01]) ** 2
            out.append((Query(e.kind, z, R, (math.nan, math.nan)), t))
        else:
            R = bind_line_cov(z, np.diag([0.02, 0.02, 0.01]) ** 2)
            out.append((Query(e.kind, z, R, extent=(-1.0, 1.0)), t))
    return out


def test_chained_jacobian_is_the_derivative_through_the_increment() -> None:
    """``_chained``'s H against central differences of the pairing residual as a
    function of the map before the motion and of the increment."""
    rng = np.random.default_rng(1)
    before = local_map(rng)
    n = len(before)
    moved = before.copy()
    predict(moved, U, Q)
    pairs = _queries(moved, rng)
    joint = before.copy()
    ui = joint.add(Element(ElementKind.POSE, Role.BASE, False, -1), U, Q)

    def residuals(x: np.ndarray) -> np.ndarray:
        view = GaussianMap()
        view.elements, view.mean = joint.elements[:n], x.reshape(-1, 3)[:n]
        moved.mean = motion(view, x.reshape(-1, 3)[ui]).mean
        return np.concatenate([evaluate(moved, q, t).residual for q, t in pairs])

    x0 = joint.mean.reshape(-1).copy()
    mo = motion(before, U)
    moved.mean = mo.mean
    H = np.zeros((sum(3 if q.kind == ElementKind.CIRCLE else 2 for q, _ in pairs), x0.size))
    row = 0
    for q, t in pairs:
        c = _chained(evaluate(moved, q, t), mo, {e: e for e in range(n)}, ui)
        for j, e in enumerate(c.indices):
            H[row : row + c.residual.size, 3 * e : 3 * e + 3] += c.H[:, 3 * j : 3 * j + 3]
        row += c.residual.size
    h = 1e-6
    num = np.zeros_like(H)
    for i in range(x0.size):
        d = np.zeros_like(x0)
        d[i] = h
        num[:, i] = (residuals(x0 + d) - residuals(x0 - d)) / (2 * h)
    # Central differences of smooth residuals of O(10 m): error ~h² · 10 ≪ 1e-6.
    np.testing.assert_allclose(H, num, atol=1e-6)


def _map_estimate(
    before: GaussianMap, z: list[tuple[np.ndarray, np.ndarray, int]]
) -> tuple[np.ndarray, np.ndarray]:
    """The maximum a posteriori ``[x^R'_E…, u]`` of one step (prior, increment and
    circle measurements), by scipy's least squares on the whitened residuals, with
    the inverse of its Gauss–Newton Hessian."""
    n = len(before)
    x0 = np.concatenate([before.mean.reshape(-1), U])
    P0 = np.zeros((x0.size, x0.size))
    P0[: 3 * n, : 3 * n] = before.cov
    P0[3 * n :, 3 * n :] = Q
    Wp = np.linalg.cholesky(np.linalg.inv(P0)).T

    def res(x: np.ndarray) -> np.ndarray:
        d = x - x0
        out = [Wp @ d]
        for zz, Rz, t in z:
            r = observe(FeatureKind.CIRCLE, zz, x[3 * n :], x[3 * t : 3 * t + 3])[0]
            out.append(np.linalg.cholesky(np.linalg.inv(Rz)).T @ r)
        return np.concatenate(out)

    sol = least_squares(res, x0, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    return sol.x, np.linalg.inv(sol.jac.T @ sol.jac)


def test_the_update_is_the_steps_maximum_a_posteriori(monkeypatch: pytest.MonkeyPatch) -> None:
    """On a rough increment the iterated update lands on the step's MAP (moved by the
    MAP increment) and its covariance is the MAP's Gauss–Newton covariance, moved to
    first order; the measured linearisation misses the MAP by millimetres.  Iterated
    to convergence (the default stops within 1e-3 σ of it)."""
    monkeypatch.setattr(increment, "RELATIVE_TOLERANCE", 1e-9)
    rng = np.random.default_rng(2)
    before = local_map(rng, lines=False)
    n = len(before)
    pred = before.copy()
    predict(pred, U, Q)
    pairs = [(q, t) for q, t in _queries(pred, rng) if q.kind == ElementKind.CIRCLE]
    # Far from the prediction: the measurements say the heading turned 0.05 rad more.
    for q, _ in pairs:
        c, s = math.cos(-0.05), math.sin(-0.05)
        q.params[:2] = [c * q.params[0] - s * q.params[1], s * q.params[0] + c * q.params[1]]
    measured = pred.copy()
    apply(measured, [evaluate(measured, q, t) for q, t in pairs])
    iterated = pred.copy()
    upd = update_through_increment(
        iterated, Increment(before.copy(), U, Q), lambda s: [evaluate(s, q, t) for q, t in pairs]
    )
    assert upd.converged
    assert upd.iterations > 1
    x_map, P_map = _map_estimate(before, [(q.params, q.cov, t) for q, t in pairs])
    view = GaussianMap()
    view.elements, view.mean = before.elements, x_map[: 3 * n].reshape(-1, 3)
    mo = motion(view, x_map[3 * n :])
    np.testing.assert_allclose(iterated.mean, mo.mean, atol=1e-7)
    # Handed the pairings at the prediction (the association's), it starts from them.
    again = pred.copy()
    update_through_increment(
        again,
        Increment(before.copy(), U, Q),
        lambda s: [evaluate(s, q, t) for q, t in pairs],
        [evaluate(pred, q, t) for q, t in pairs],
    )
    np.testing.assert_array_equal(again.mean, iterated.mean)
    np.testing.assert_array_equal(again.cov, iterated.cov)
    assert np.abs(measured.mean - mo.mean)[:, :2].max() > 1e-3
    F = np.zeros((3 * n, 3 * n + 3))
    for i in range(n):
        F[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = mo.rotation if mo.moving[i] else np.eye(3)
    F[:, 3 * n :] = mo.increment_jacobian
    # The reference's Hessian is from least_squares' 2-point differences: ~1e-9 off.
    np.testing.assert_allclose(iterated.cov, F @ P_map @ F.T, atol=1e-8)


def test_a_map_that_grew_since_the_prediction_is_refused() -> None:
    before = local_map(np.random.default_rng(3))
    pred = before.copy()
    predict(pred, U, Q)
    pred.add(Element(ElementKind.CIRCLE, Role.FEATURE, True, 99), np.ones(3), np.eye(3))
    with pytest.raises(ValueError, match="elements were added in between"):
        update_through_increment(pred, Increment(before, U, Q), lambda s: [])


def test_unknown_linearisation_is_refused() -> None:
    with pytest.raises(ValueError, match="odometry_linearisation must be one of"):
        EKFConfig(odometry_linearisation="exact")  # type: ignore[arg-type]


def test_paper_preset_linearises_at_the_measured_increment() -> None:
    assert EKFConfig.paper().odometry_linearisation == "measured"


def _anees(mode: str, sigma_odo: tuple[float, float, float], seeds: range) -> list[float]:
    out = []
    world = ring_world(n_circles=24, n_lines=6)
    for seed in seeds:
        log = synthetic_log(steps=300, seed=seed, sigma_odo=sigma_odo, world=world)
        res = run_ekf(log, EKFConfig(odometry_linearisation=mode), fusion=False)
        assert res.details.increment_unconverged == 0
        err = pose_errors(res.poses, truth_in_global(log.true_poses))
        out.append(float(np.nanmean(nees_series(err.dx, res.covs)[1:])))
    return out


def test_rough_odometry_keeps_the_iterated_ekf_consistent() -> None:
    """Heading σ 0.03 rad a step on the synthetic ring, seeds 1–4 (300 steps each):
    the measured linearisation is two orders overconfident, the iterated one is not.
    Measured: ANEES 4.1 iterated (runs 2.1–6.2), above 80 for every measured run.  6
    is twice the expectation of a 3-dof NEES, far below the measured runs."""
    seeds = range(1, 5)
    measured = _anees("measured", (0.05, 0.02, 0.03), seeds)
    iterated = _anees("iterated", (0.05, 0.02, 0.03), seeds)
    assert min(measured) > 50.0
    assert float(np.mean(iterated)) < 6.0


def test_smooth_odometry_gives_the_measured_linearisation_back() -> None:
    """With a heading σ of 0.0005 rad a step the two agree to 0.5 % of σ (measured)
    and 0.1 % on variances: the iterated update changes the linearisation, not the
    model.  The gap is second order in the heading σ: at 0.002 rad (the ring's
    default) it is 9 % of σ."""
    log = synthetic_log(steps=200, seed=0, sigma_odo=(0.01, 0.005, 0.0005))
    a = run_ekf(log, EKFConfig(), fusion=False)
    b = run_ekf(log, EKFConfig(odometry_linearisation="iterated"), fusion=False)
    d = b.poses - a.poses
    sig = np.sqrt(np.diagonal(a.covs, axis1=1, axis2=2))[1:]
    assert np.all(np.abs(d[1:]) <= 0.01 * sig)
    np.testing.assert_allclose(
        np.diagonal(b.covs, axis1=1, axis2=2)[1:],
        np.diagonal(a.covs, axis1=1, axis2=2)[1:],
        rtol=0.002,
    )
