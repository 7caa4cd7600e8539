"""GTSAM factors: residuals are the shared model, Jacobians are exact in GTSAM's tangents."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import gtsam
import numpy as np
import pytest
from gtsam.utils.numerical_derivative import numericalDerivative21, numericalDerivative22
from hypothesis import assume, given
from hypothesis import strategies as st

from mapfuse_core.geometry.features import FeatureKind, line_from_normal, transform_feature
from mapfuse_core.geometry.se2 import compose, inverse, wrap_angle, wrap_angle_half
from mapfuse_core.models import observe, pairing_residual
from mapfuse_graph import factors as fx
from tests.jacobians import angle, circles, coord, numerical_jacobian, poses

ErrorOut = tuple[np.ndarray, Sequence[np.ndarray]]

# Keys of the test graphs.
X, L, A, K = 1, 2, 3, 4


pytestmark = pytest.mark.usefixtures("jacobian_checks")


rho_alpha = st.builds(
    lambda r, a: np.array([r, a]),
    st.floats(min_value=-60.0, max_value=60.0, allow_nan=False),
    angle,
)
line_meas = st.builds(
    lambda x, y, t: np.array([x, y, float(wrap_angle(t))]),
    st.floats(min_value=-30.0, max_value=30.0, allow_nan=False),
    st.floats(min_value=-30.0, max_value=30.0, allow_nan=False),
    angle,
)


def _pose2(p: np.ndarray) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def _tangent_jacobians(
    factor: gtsam.CustomFactor, values: gtsam.Values, angle_rows: tuple[int, ...], h: float = 1e-6
) -> list[np.ndarray]:
    """Central differences of ``unwhitenedError`` in each key's GTSAM tangent.

    Pose2 keys are perturbed by ``retract`` (body frame), vector keys by addition.
    Angle rows are differenced through a wrap modulo π (line angles) so a residual
    that jumps across ±π/2 is still differentiated right.
    """
    out = []
    for key in list(factor.keys()):
        is_pose = True
        try:
            base_pose = values.atPose2(key)
            d = 3
        except RuntimeError:
            is_pose = False
            base_vec = np.asarray(values.atVector(key), dtype=float)
            d = base_vec.size
        cols = []
        for i in range(d):
            diffs = []
            for sgn in (1.0, -1.0):
                delta = np.zeros(d)
                delta[i] = sgn * h
                v = gtsam.Values(values)
                if is_pose:
                    v.update(key, base_pose.retract(delta))
                else:
                    v.update(key, base_vec + delta)
                diffs.append(np.asarray(factor.unwhitenedError(v), dtype=float))
            dr = diffs[0] - diffs[1]
            for r in angle_rows:
                dr[r] = (dr[r] + math.pi / 2) % math.pi - math.pi / 2
            cols.append(dr / (2 * h))
        out.append(np.column_stack(cols))
    return out


def _analytic(factor: gtsam.CustomFactor, values: gtsam.Values) -> list[np.ndarray]:
    dims = []
    for key in list(factor.keys()):
        try:
            values.atPose2(key)
            dims.append(3)
        except RuntimeError:
            dims.append(int(np.asarray(values.atVector(key)).size))
    m = factor.dim()
    H = gtsam.JacobianVector([np.zeros((m, d)) for d in dims])
    factor.unwhitenedError(values, H)
    return [np.asarray(J) for J in H]


def _assert_close(Ja: list[np.ndarray], Jn: list[np.ndarray], scale: float) -> None:
    # Central differences with h = 1e-6 on inputs of magnitude ≲ 100 m: truncation
    # ~1e-12, round-off ~1e-10·|r|/1e-6 ≲ 1e-7 · scale.
    for a, n in zip(Ja, Jn, strict=True):
        assert a.shape == n.shape
        np.testing.assert_allclose(a, n, atol=2e-6 * max(1.0, scale), rtol=1e-5)


# --------------------------------------------------------------------------- pure models


def _not_perpendicular(r: np.ndarray, margin: float = 1e-3) -> None:
    """Skip a draw whose line angle residual is within ``margin`` of ±π/2.

    There the line model is discontinuous (the angle wraps modulo π and the lateral
    offset's orientation follows the nearer direction), so a central difference
    straddling it is meaningless; such a pair is never an association.
    """
    assume(abs(abs(float(r[1])) - math.pi / 2) > margin)


@given(z=line_meas, x=poses(), ra=rho_alpha, t=coord)
def test_line_observation_error_is_the_core_model_wherever_the_landmark_frame_is(
    z: np.ndarray, x: np.ndarray, ra: np.ndarray, t: float
) -> None:
    # The landmark's SPmap frame may sit anywhere along its line: same residual.
    r, _, _ = fx.line_observation_error(z, x, ra)
    f, _ = line_from_normal(float(ra[0]), float(ra[1]), t)
    scale = 1.0 + float(np.abs(x[:2]).max() + abs(ra[0]) + abs(t) + np.abs(z[:2]).max())
    r_core = observe(FeatureKind.LINE, z, x, f)[0]
    assert abs(r[0] - r_core[0]) <= 1e-12 * scale
    assert abs(float(wrap_angle_half(r[1] - r_core[1]))) <= 1e-12
    np.testing.assert_allclose(fx.line_observation_residual(z, x, ra), r, atol=1e-12)
    # The lateral residual is the offset of the observed midpoint from the line.
    p = compose(x, z)
    e = ra[0] - p[0] * math.cos(ra[1]) - p[1] * math.sin(ra[1])
    assert abs(abs(r[0]) - abs(e)) <= 1e-12 * scale


@given(z=line_meas, x=poses())
def test_line_residual_zero_on_the_observed_line(z: np.ndarray, x: np.ndarray) -> None:
    ra = fx.landmark_from_observation(FeatureKind.LINE, x, z)
    r, _, _ = fx.line_observation_error(z, x, ra)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)


@given(z=line_meas, x=poses(), ra=rho_alpha)
def test_line_observation_jacobians_raw(z: np.ndarray, x: np.ndarray, ra: np.ndarray) -> None:
    r, Jx, Jl = fx.line_observation_error(z, x, ra)
    _not_perpendicular(r)
    Jx_n = numerical_jacobian(lambda v: fx.line_observation_error(z, v, ra)[0], x, (1,))
    Jl_n = numerical_jacobian(lambda v: fx.line_observation_error(z, x, v)[0], ra, (1,))
    scale = float(np.abs(x[:2]).max() + np.abs(ra[0]) + 50.0)
    _assert_close([Jx, Jl], [Jx_n, Jl_n], scale)


@given(line=line_meas)
def test_rho_alpha_round_trip(line: np.ndarray) -> None:
    ra, J = fx.line_to_rho_alpha(line)
    t = fx.rho_alpha_along(ra, line)
    back, _ = line_from_normal(float(ra[0]), float(ra[1]), t)
    np.testing.assert_allclose(back[:2], line[:2], atol=1e-9)
    assert abs(float(wrap_angle(back[2] - line[2]))) < 1e-9
    Jn = numerical_jacobian(lambda v: fx.line_to_rho_alpha(v)[0], line, (1,))
    np.testing.assert_allclose(J, Jn, atol=1e-6)


def test_rho_alpha_is_smooth_through_the_origin() -> None:
    # A line sliding across the origin: ρ changes sign, α does not jump.
    ras = [fx.line_to_rho_alpha(np.array([0.0, y, 0.3]))[0] for y in (-1e-3, 0.0, 1e-3)]
    assert ras[0][0] > 0 > ras[2][0]
    assert max(abs(r[1] - ras[1][1]) for r in ras) < 1e-12


# --------------------------------------------------------------------------- factors


@given(z=line_meas, x=poses(), ra=rho_alpha)
def test_line_factor_jacobians(z: np.ndarray, x: np.ndarray, ra: np.ndarray) -> None:
    _not_perpendicular(fx.line_observation_error(z, x, ra)[0])
    f = fx.line_factor(X, L, z, gtsam.noiseModel.Unit.Create(2))
    v = gtsam.Values()
    v.insert(X, _pose2(x))
    v.insert(L, ra)
    scale = float(np.abs(x[:2]).max() + abs(ra[0]) + 50.0)
    _assert_close(_analytic(f, v), _tangent_jacobians(f, v, (1,)), scale)


# The factor callbacks are closed forms of the shared model (speed, see the factors
# module docstring); these hold them to it.  The two paths round differently: the
# shared one goes through ~20 intermediate arrays, so agreement is to a few ulps of
# the inputs' magnitude (measured worst 7e-16 × scale over 20k random draws), and
# 1e-12 × scale still fails any wrong term.
# The α variable is never wrapped, so values beyond ±π are legal inputs too.
unwrapped_rho_alpha = st.one_of(
    rho_alpha,
    st.builds(
        lambda r, a: np.array([r, a]),
        st.floats(min_value=-60.0, max_value=60.0, allow_nan=False),
        st.floats(min_value=-4 * math.pi, max_value=4 * math.pi, allow_nan=False),
    ),
)


def _callback_outputs(
    factor: gtsam.CustomFactor, values: gtsam.Values, dims: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray]]:
    """Residual of the error-only call, and residual and Jacobians of the linearising one."""
    m = factor.dim()
    H = gtsam.JacobianVector([np.zeros((m, d)) for d in dims])
    r_lin = np.asarray(factor.unwhitenedError(values, H), dtype=float)
    r_err = np.asarray(factor.unwhitenedError(values), dtype=float)
    return r_err, r_lin, [np.asarray(J) for J in H]


@given(z=line_meas, x=poses(), ra=unwrapped_rho_alpha)
def test_line_factor_is_the_shared_model(z: np.ndarray, x: np.ndarray, ra: np.ndarray) -> None:
    f = fx.line_factor(X, L, z, gtsam.noiseModel.Unit.Create(2))
    v = gtsam.Values()
    v.insert(X, _pose2(x))
    v.insert(L, ra)
    xv = fx.pose_of(v.atPose2(X))  # the pose exactly as the callback reads it
    r_ref, Jx_ref, Jl_ref = fx.line_observation_error(z, xv, ra)
    # Exactly perpendicular, the two paths' round-off may pick opposite orientations.
    _not_perpendicular(r_ref, 1e-9)
    J_ref = [fx.to_body(Jx_ref, float(xv[2])), Jl_ref]
    r_err, r_lin, J = _callback_outputs(f, v, (3, 2))
    tol = 1e-12 * (1.0 + float(np.abs(xv[:2]).max() + abs(ra[0]) + np.abs(z[:2]).max()))
    for r in (r_err, r_lin):
        assert abs(r[0] - r_ref[0]) <= tol
        # Angles modulo π: a residual of exactly ±π/2 may land on either end.
        assert abs(float(wrap_angle_half(r[1] - r_ref[1]))) <= tol
    for a, b in zip(J, J_ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=tol)


@given(z=circles(), x=poses(), c=circles())
def test_circle_factor_is_the_shared_model(z: np.ndarray, x: np.ndarray, c: np.ndarray) -> None:
    f = fx.circle_factor(X, L, z, gtsam.noiseModel.Unit.Create(3))
    v = gtsam.Values()
    v.insert(X, _pose2(x))
    v.insert(L, c)
    xv = fx.pose_of(v.atPose2(X))
    r_ref, Jx_ref, Jc_ref = fx.circle_observation_error(z, xv, c)
    J_ref = [fx.to_body(Jx_ref, float(xv[2])), Jc_ref]
    r_err, r_lin, J = _callback_outputs(f, v, (3, 3))
    tol = 1e-12 * (1.0 + float(np.abs(xv[:2]).max() + np.abs(c[:2]).max()))
    np.testing.assert_allclose(r_err, r_ref, rtol=0.0, atol=tol)
    np.testing.assert_allclose(r_lin, r_ref, rtol=0.0, atol=tol)
    for a, b in zip(J, J_ref, strict=True):
        np.testing.assert_allclose(a, b, rtol=0.0, atol=tol)


def test_reused_jacobian_buffers_do_not_leak_between_linearisations() -> None:
    # The callbacks refill one Jacobian buffer per factor; GTSAM must have copied the
    # previous linearisation's Jacobians, not kept a view of the buffer.
    line = fx.line_factor(X, L, np.array([3.0, 1.0, 0.4]), gtsam.noiseModel.Unit.Create(2))
    circle = fx.circle_factor(X, K, np.array([2.0, -1.0, 0.5]), gtsam.noiseModel.Unit.Create(3))
    g = gtsam.NonlinearFactorGraph()
    g.add(line)
    g.add(circle)

    def values(x: np.ndarray) -> gtsam.Values:
        v = gtsam.Values()
        v.insert(X, _pose2(x))
        v.insert(L, np.array([5.0, 0.2]))
        v.insert(K, np.array([4.0, 1.0, 0.6]))
        return v

    v1, v2 = values(np.array([1.0, 2.0, 0.3])), values(np.array([-4.0, 0.5, 2.9]))
    first = g.linearize(v1).jacobian()[0].copy()
    lin1 = g.linearize(v1)
    g.linearize(v2)
    np.testing.assert_array_equal(lin1.jacobian()[0], first)
    assert not np.allclose(g.linearize(v2).jacobian()[0], first)


@given(z=circles(), x=poses(), c=circles())
def test_circle_factor_jacobians(z: np.ndarray, x: np.ndarray, c: np.ndarray) -> None:
    f = fx.circle_factor(X, L, z, gtsam.noiseModel.Unit.Create(3))
    v = gtsam.Values()
    v.insert(X, _pose2(x))
    v.insert(L, c)
    r = np.asarray(f.unwhitenedError(v))
    np.testing.assert_allclose(r, observe(FeatureKind.CIRCLE, z, x, c)[0], atol=1e-12)
    _assert_close(_analytic(f, v), _tangent_jacobians(f, v, ()), float(np.abs(x).max() + 50))


@given(a=poses(), ra=rho_alpha, k=rho_alpha, t=coord)
def test_line_tie_factor_jacobians(a: np.ndarray, ra: np.ndarray, k: np.ndarray, t: float) -> None:
    _not_perpendicular(fx.line_tie_error(a, ra, k, t)[0])
    f = fx.line_tie_factor(A, L, K, t, gtsam.noiseModel.Unit.Create(2))
    v = gtsam.Values()
    v.insert(A, _pose2(a))
    v.insert(L, ra)
    v.insert(K, k)
    scale = float(np.abs(a[:2]).max() + abs(ra[0]) + abs(k[0]) + abs(t) + 50.0)
    _assert_close(_analytic(f, v), _tangent_jacobians(f, v, (1,)), scale)


@given(ra=rho_alpha, k=line_meas)
def test_known_line_prior_jacobian(ra: np.ndarray, k: np.ndarray) -> None:
    _not_perpendicular(fx.known_line_prior_error(ra, k)[0])
    f = fx.known_line_prior_factor(K, k, np.diag([0.01, 0.01, 0.0025]))
    v = gtsam.Values()
    v.insert(K, ra)
    scale = float(abs(ra[0]) + np.abs(k[:2]).max() + 50.0)
    _assert_close(_analytic(f, v), _tangent_jacobians(f, v, (1,)), scale)


@given(k=line_meas, t=coord)
def test_known_line_prior_is_zero_on_the_surveyed_wall(k: np.ndarray, t: float) -> None:
    # Any point of the wall gives the same (ρ, α): the prior has no along-line term.
    f = line_from_normal(*fx.line_to_rho_alpha(k)[0], t)[0]
    r, _ = fx.known_line_prior_error(fx.line_to_rho_alpha(f)[0], k)
    np.testing.assert_allclose(r, 0.0, atol=1e-9 * (1.0 + np.abs(k[:2]).max() + abs(t)))


def test_known_line_prior_noise_is_the_lateral_angle_block() -> None:
    # A wall along x (θ₀ = 0): lateral is y, so the residual covariance picks σy², σθ²
    # and their covariance, whatever the along-line σx.
    cov = np.array([[4.0, 0.1, 0.2], [0.1, 0.09, 0.003], [0.2, 0.003, 0.0025]])
    S = fx.known_line_prior_cov(np.array([30.0, 5.0, 0.0]), cov)
    np.testing.assert_allclose(S, [[0.09, 0.003], [0.003, 0.0025]], atol=1e-15)
    with pytest.raises(ValueError, match="known line"):
        fx.known_line_prior_factor(K, np.array([0.0, np.nan, 0.0]), cov)


@given(a=poses(), c=circles(), k=circles())
def test_circle_tie_factor_jacobians(a: np.ndarray, c: np.ndarray, k: np.ndarray) -> None:
    f = fx.circle_tie_factor(A, L, K, gtsam.noiseModel.Unit.Create(3))
    v = gtsam.Values()
    v.insert(A, _pose2(a))
    v.insert(L, c)
    v.insert(K, k)
    _assert_close(_analytic(f, v), _tangent_jacobians(f, v, ()), float(np.abs(a).max() + 50))


@given(a=poses(), k=line_meas)
def test_tie_residual_is_zero_for_the_transformed_known_feature(
    a: np.ndarray, k: np.ndarray
) -> None:
    # L = A ⊕ K exactly: the line tie is zero whatever the reference point t_known.
    kra = fx.line_to_rho_alpha(k)[0]
    lra = fx.line_to_rho_alpha(transform_feature(FeatureKind.LINE, a, k)[0])[0]
    for t in (-20.0, 0.0, fx.rho_alpha_along(kra, k), 35.0):
        np.testing.assert_allclose(fx.line_tie_error(a, lra, kra, t)[0], 0.0, atol=1e-8)
    c = np.array([k[0], k[1], 0.5])
    cw = transform_feature(FeatureKind.CIRCLE, a, c)[0]
    np.testing.assert_allclose(fx.circle_tie_error(a, cw, c)[0], 0.0, atol=1e-9)


def test_jacobians_match_gtsam_numerical_derivative() -> None:
    """Cross-check with GTSAM's own numerical derivatives (away from θ = ±π)."""
    rng = np.random.default_rng(3)
    for _ in range(20):
        x = np.array([*rng.uniform(-20, 20, 2), rng.uniform(-2.5, 2.5)])
        z = np.array([*rng.uniform(-10, 10, 2), rng.uniform(-1.2, 1.2)])
        ra = fx.landmark_from_observation(FeatureKind.LINE, x, z) + rng.normal(0, [0.3, 0.05])
        f = fx.line_factor(X, L, z, gtsam.noiseModel.Unit.Create(2))
        v = gtsam.Values()
        v.insert(X, _pose2(x))
        v.insert(L, ra)

        def err(p: gtsam.Pose2, lv: np.ndarray, f: gtsam.CustomFactor = f) -> np.ndarray:
            w = gtsam.Values()
            w.insert(X, p)
            w.insert(L, np.asarray(lv, dtype=float))
            return np.asarray(f.unwhitenedError(w))

        Ja = _analytic(f, v)
        J0 = numericalDerivative21(err, _pose2(x), ra, delta=1e-6)
        J1 = numericalDerivative22(err, _pose2(x), ra, delta=1e-6)
        np.testing.assert_allclose(Ja[0], J0, atol=1e-5)
        np.testing.assert_allclose(Ja[1], J1, atol=1e-5)


@given(p=poses())
def test_to_body_matches_pose2_retract(p: np.ndarray) -> None:
    # d(X.retract(δ))/dδ in raw (x, y, θ) is blockdiag(R(θ), 1): to_body(I) must equal it.
    G = fx.to_body(np.eye(3), float(p[2]))
    base = _pose2(p)

    def raw(d: np.ndarray) -> np.ndarray:
        return fx.pose_of(base.retract(d))

    Jn = numerical_jacobian(raw, np.zeros(3), (2,))
    np.testing.assert_allclose(G, Jn, atol=1e-6)


# --------------------------------------------------------------------------- noise


@given(z=line_meas, th=angle)
def test_line_noise_is_the_lateral_angle_block(z: np.ndarray, th: float) -> None:
    del th
    c, s = math.cos(z[2]), math.sin(z[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = np.array([[4.0, 0.3, 0.02], [0.3, 0.01, 0.001], [0.02, 0.001, 0.0004]])
    cov = R @ local @ R.T
    P = fx.residual_noise_cov(FeatureKind.LINE, z, cov)
    # Lateral/angle block in the line's own frame; the along-line variance never enters.
    np.testing.assert_allclose(P, local[1:, 1:], atol=1e-10)


def test_circle_noise_is_the_observation_covariance() -> None:
    cov = np.array([[1e-3, 2e-4, 0.0], [2e-4, 2e-3, 0.0], [0.0, 0.0, 5e-4]])
    np.testing.assert_allclose(
        fx.residual_noise_cov(FeatureKind.CIRCLE, np.array([3.0, 1.0, 0.4]), cov), cov
    )


def test_line_residual_covariance_monte_carlo() -> None:
    """Observations drawn from their covariance give residuals of the stated covariance."""
    rng = np.random.default_rng(0)
    x = np.array([2.0, -1.0, 0.4])
    truth_line = np.array([10.0, 5.0, 2.0])
    ra = fx.line_to_rho_alpha(truth_line)[0]
    z0 = transform_feature(FeatureKind.LINE, inverse(x), truth_line)[0]  # noise-free z
    c, s = math.cos(z0[2]), math.sin(z0[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = np.diag([4.0, 0.02**2, 0.005**2])
    rs = []
    for _ in range(4000):
        d = rng.multivariate_normal(np.zeros(3), local)
        z = compose(z0, d)  # noise in the line's own frame, as the simulator draws it
        rs.append(fx.line_observation_error(z, x, ra)[0])
    emp = np.cov(np.array(rs).T)
    P = fx.residual_noise_cov(FeatureKind.LINE, z0, R @ local @ R.T)
    np.testing.assert_allclose(np.sqrt(np.diag(emp)), np.sqrt(np.diag(P)), rtol=0.06)


def test_make_noise_rejects_bad_covariances() -> None:
    with pytest.raises(ValueError, match="positive definite"):
        fx.make_noise(np.diag([1.0, 0.0]))
    with pytest.raises(ValueError, match="symmetric"):
        fx.make_noise(np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="finite"):
        fx.make_noise(np.array([[np.nan, 0.0], [0.0, 1.0]]))


@pytest.mark.parametrize("spec", ["huber", "cauchy", "huber:2.5", "cauchy:0.5"])
def test_robust_kernels_downweight_outliers(spec: str) -> None:
    z = np.array([3.0, 2.0, 0.3])
    f = fx.circle_factor(X, L, z, fx.make_noise(np.eye(3) * 0.01, spec))
    g = fx.circle_factor(X, L, z, fx.make_noise(np.eye(3) * 0.01))
    v = gtsam.Values()
    v.insert(X, gtsam.Pose2())
    v.insert(L, z + np.array([5.0, 0.0, 0.0]))  # a 50 σ outlier
    assert f.error(v) < 0.2 * g.error(v)


@pytest.mark.parametrize("spec", ["tukey", "huber:-1", "huber:abc"])
def test_bad_robust_spec(spec: str) -> None:
    with pytest.raises(ValueError, match="robust"):
        fx.make_noise(np.eye(2), spec)


# --------------------------------------------------------------------------- guards


def _wrong(shape: tuple[int, ...]) -> Callable[[gtsam.Values, Sequence[int]], ErrorOut]:
    def error(values: gtsam.Values, keys: Sequence[int]) -> ErrorOut:
        del values, keys
        return np.zeros(2), [np.zeros(shape)]

    return error


@pytest.mark.parametrize("shape", [(2, 3), (3, 2), (2,), (1, 2)])
def test_shape_guard_fires_instead_of_segfault(shape: tuple[int, ...]) -> None:
    # (2, 3) and (2,) are silently accepted by GTSAM (wrong system); (3, 2), (1, 2)
    # would segfault in linearize().  The guard turns all into a Python error.
    f = fx.custom_factor(gtsam.noiseModel.Unit.Create(2), [L], [2], _wrong(shape), "wrong")
    v = gtsam.Values()
    v.insert(L, np.zeros(2))
    g = gtsam.NonlinearFactorGraph()
    g.add(f)
    with pytest.raises(fx.JacobianShapeError, match="wrong: Jacobian 0 has shape"):
        g.linearize(v)


def test_shape_guard_accepts_right_shapes_and_can_be_switched_off() -> None:
    f = fx.custom_factor(gtsam.noiseModel.Unit.Create(2), [L], [2], _wrong((2, 2)), "right")
    v = gtsam.Values()
    v.insert(L, np.zeros(2))
    g = gtsam.NonlinearFactorGraph()
    g.add(f)
    g.linearize(v)
    fx.set_jacobian_checks(False)
    assert not fx.jacobian_checks_enabled()
    g.linearize(v)


def test_guard_catches_non_finite_jacobians_of_real_factors() -> None:
    f = fx.circle_factor(X, L, np.array([1.0, 0.0, 0.5]), gtsam.noiseModel.Unit.Create(3))
    v = gtsam.Values()
    v.insert(X, gtsam.Pose2())
    v.insert(L, np.array([np.nan, 0.0, 0.5]))
    g = gtsam.NonlinearFactorGraph()
    g.add(f)
    with pytest.raises(fx.JacobianShapeError, match="non-finite"):
        g.linearize(v)


def test_factor_constructors_validate() -> None:
    unit2, unit3 = gtsam.noiseModel.Unit.Create(2), gtsam.noiseModel.Unit.Create(3)
    with pytest.raises(ValueError, match="2-dim"):
        fx.line_factor(X, L, np.zeros(3), unit3)
    with pytest.raises(ValueError, match="3-dim"):
        fx.circle_factor(X, L, np.array([1.0, 1.0, 0.5]), unit2)
    with pytest.raises(ValueError, match="radius"):
        fx.circle_factor(X, L, np.array([1.0, 1.0, 0.0]), unit3)
    with pytest.raises(ValueError, match="finite"):
        fx.line_factor(X, L, np.array([np.nan, 0.0, 0.0]), unit2)
    with pytest.raises(ValueError, match="finite"):
        fx.line_factor(X, L, np.zeros(2), unit2)
    with pytest.raises(ValueError, match="t_known"):
        fx.line_tie_factor(A, L, K, math.inf, unit2)
    with pytest.raises(ValueError, match="unknown feature kind"):
        fx.observation_factor(7, X, L, np.zeros(3), np.eye(3))  # type: ignore[arg-type]


def test_line_noise_jacobian_is_the_pairing_jacobian() -> None:
    # The noise model is ∂pairing(f, z)/∂z at f = z: check against features directly.
    z = np.array([4.0, -2.0, 0.7])
    _, _, Jz = pairing_residual(FeatureKind.LINE, z, z)
    cov = np.diag([1.0, 0.04, 0.001])
    np.testing.assert_allclose(fx.residual_noise_cov(FeatureKind.LINE, z, cov), Jz @ cov @ Jz.T)
