"""The measurement models of mapfuse_core.models, and the fast copies held equal to them."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from ekf_reference.association import predict_all_targets
from ekf_reference.maps import predict
from ekf_reference.state import Element, ElementKind, GaussianMap, Role
from mapfuse_core.geometry import features as ft
from mapfuse_core.geometry.se2 import compose, compose_jacobians, relative, wrap_angle_half
from mapfuse_core.models import (
    bind_line_cov,
    circle_observation,
    circle_observation_cov,
    circle_residual,
    circle_residual_cov,
    line_observation,
    line_observation_cov,
    line_residual,
    line_residual_cov,
    observe,
    pairing_cov,
    pairing_residual,
)
from tests.jacobians import ATOL, RTOL, angle, circles, coord, numerical_jacobian, poses

slides = st.floats(min_value=-50.0, max_value=50.0, allow_nan=False)
small = st.floats(min_value=-0.3, max_value=0.3, allow_nan=False)


def _slide(line: np.ndarray, s: float) -> tuple[np.ndarray, np.ndarray]:
    """The same line with its reference point ``s`` metres along it, and ∂(slid)/∂line."""
    new, J, _ = compose_jacobians(line, np.array([s, 0.0, 0.0]))
    return new, J


def _segment_cov(line: np.ndarray, along: float, lat: float, ang: float) -> np.ndarray:
    """Covariance of a segment with σ² ``along`` on its own axis, ``lat`` across, ``ang``."""
    c, s = math.cos(line[2]), math.sin(line[2])
    Rm = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    local = np.array([[along, 0.0, 0.0], [0.0, lat, 1e-5], [0.0, 1e-5, ang]])
    out: np.ndarray = Rm @ local @ Rm.T
    return out


def _not_perpendicular(r: np.ndarray) -> None:
    """Skip a draw within 1 mrad of perpendicular lines, where the line model is
    discontinuous (angle modulo π, lateral orientation): no association is there."""
    assume(abs(abs(float(r[1])) - math.pi / 2) > 1e-3)


# --------------------------------------------------------------------------- line


@given(T=poses(), Z=poses())
def test_line_residual_jacobians(T: np.ndarray, Z: np.ndarray) -> None:
    r, JT, JZ = line_residual(T, Z)
    _not_perpendicular(r)
    assert r.shape == (2,)
    assert -math.pi / 2 < r[1] <= math.pi / 2
    np.testing.assert_allclose(
        JT, numerical_jacobian(lambda x: line_residual(x, Z)[0], T, (1,)), atol=ATOL, rtol=RTOL
    )
    np.testing.assert_allclose(
        JZ, numerical_jacobian(lambda x: line_residual(T, x)[0], Z, (1,)), atol=ATOL, rtol=RTOL
    )


@given(T=poses(), along=coord, lat=small, ang=small)
def test_line_residual_is_the_midpoints_offset_and_the_angle(
    T: np.ndarray, along: float, lat: float, ang: float
) -> None:
    Z = compose(T, np.array([along, lat, ang]))
    r, _, _ = line_residual(T, Z)
    np.testing.assert_allclose(r, [lat, ang], atol=1e-10)
    # A line has no direction: T turned by π gives the same residual (the offset is
    # measured along T's normal oriented like Z's).
    r_flip, _, _ = line_residual(compose(T, np.array([0.0, 0.0, math.pi])), Z)
    np.testing.assert_allclose(r_flip, [lat, ang], atol=1e-10)


@given(Z=poses(), along=st.floats(min_value=0.0, max_value=1e4), turn=st.booleans())
def test_line_noise_does_not_depend_on_the_targets_direction(
    Z: np.ndarray, along: float, turn: bool
) -> None:
    # At the zero-residual point the target may point either way along the segment;
    # the lateral/angle correlation keeps the segment's sign.
    T = compose(Z, np.array([3.0, 0.0, math.pi if turn else 0.0]))
    cov = _segment_cov(Z, along, 0.01**2, 0.002**2)
    np.testing.assert_allclose(
        line_residual_cov(T, Z, cov), line_residual_cov(Z, Z, cov), atol=1e-15
    )


@given(T=poses(), Z=poses())
def test_line_residual_at_the_target_jacobians(T: np.ndarray, Z: np.ndarray) -> None:
    r, JT, JZ = line_residual(T, Z, "target")
    _not_perpendicular(r)
    assert -math.pi / 2 < r[1] <= math.pi / 2

    def f(x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return line_residual(x, y, "target")[0]

    np.testing.assert_allclose(
        JT, numerical_jacobian(lambda x: f(x, Z), T, (1,)), atol=ATOL, rtol=RTOL
    )
    np.testing.assert_allclose(
        JZ, numerical_jacobian(lambda x: f(T, x), Z, (1,)), atol=ATOL, rtol=RTOL
    )


@given(Z=poses(), along=coord, lat=small, ang=small)
def test_line_residual_at_the_target_is_the_papers_form(
    Z: np.ndarray, along: float, lat: float, ang: float
) -> None:
    """The target's reference point in the observed line's frame, bound: the paper's
    ``B · x^F_G`` (eqs. 5 and 20), negated so that it is zero where ``G`` lies on
    ``F`` and its sign is the observed form's."""
    T = compose(Z, np.array([along, lat, ang]))
    r, _, _ = line_residual(T, Z, "target")
    np.testing.assert_allclose(r, [-lat, -ang], atol=1e-10)
    np.testing.assert_allclose(r, -(relative(Z, T)[0][1:]), atol=1e-10)


@given(T=poses(), s=slides, lat=small, flip=st.booleans())
def test_line_residual_forms_coincide_for_parallel_lines(
    T: np.ndarray, s: float, lat: float, flip: bool
) -> None:
    """Parallel (or opposite) lines: both forms give the same residual wherever the
    reference points lie; with the points on one normal, the same Jacobians too."""
    Z = compose(T, np.array([s, lat, math.pi if flip else 0.0]))
    ro, JTo, JZo = line_residual(T, Z, "observed")
    rt, JTt, JZt = line_residual(T, Z, "target")
    scale = 1.0 + float(np.abs(T[:2]).max()) + abs(s)
    np.testing.assert_allclose(rt, ro, atol=1e-12 * scale)
    np.testing.assert_allclose(JTt[:, :2], JTo[:, :2], atol=1e-12)
    np.testing.assert_allclose(JZt[:, :2], JZo[:, :2], atol=1e-12)
    # The angle columns carry the lever arm (along-line distance between the points),
    # on T's angle in one form and on Z's in the other.
    assert abs(JTo[0, 2] + JZo[0, 2] - (JTt[0, 2] + JZt[0, 2])) <= 1e-12 * scale
    Zn = compose(T, np.array([0.0, lat, math.pi if flip else 0.0]))
    for a, b in zip(line_residual(T, Zn, "observed"), line_residual(T, Zn, "target"), strict=True):
        np.testing.assert_allclose(a, b, atol=1e-12 * scale)


def test_line_residual_forms_differ_by_the_lever_arm() -> None:
    """The observed reference point on the target line, 10 m behind the target's, and
    the observed line turned by δ: the target's point is 10 sin δ to the observed
    line's right, so the offset at it is 10 sin δ and the observed form's is 0."""
    T = np.array([2.0, 1.0, 0.3])
    d = 0.02
    Z = compose(T, np.array([-10.0, 0.0, d]))
    ro, _, _ = line_residual(T, Z, "observed")
    rt, _, _ = line_residual(T, Z, "target")
    assert abs(ro[0]) < 1e-12  # Z's point lies on T
    assert rt[0] == pytest.approx(10.0 * math.sin(d), abs=1e-12)
    with pytest.raises(ValueError, match="at must be"):
        line_residual(T, Z, "segment")  # type: ignore[arg-type]


@given(T=poses(), Z=poses(), s=slides)
def test_line_residual_ignores_where_the_targets_reference_point_lies(
    T: np.ndarray, Z: np.ndarray, s: float
) -> None:
    scale = 1.0 + float(np.abs(T[:2]).max() + np.abs(Z[:2]).max() + abs(s))
    r1, _, JZ1 = line_residual(T, Z)
    r2, _, JZ2 = line_residual(_slide(T, s)[0], Z)
    assert abs(r2[0] - r1[0]) <= 1e-12 * scale
    assert abs(float(wrap_angle_half(r2[1] - r1[1]))) <= 1e-12
    np.testing.assert_allclose(JZ2, JZ1, atol=1e-12)
    # Through the line's two real degrees of freedom (signed normal form, the frame
    # ``t`` metres from the foot): residual and Jacobian are the same for every t,
    # and the derivative along the line is zero.
    th = float(T[2])
    rho, alpha = T[0] * math.sin(th) - T[1] * math.cos(th), th - math.pi / 2
    J_ref = None
    for t in (-30.0, 0.0, 12.5, s):
        L, JL = ft.line_from_normal(rho, alpha, t)
        r, JT, _ = line_residual(L, Z)
        assert abs(r[0] - r1[0]) <= 1e-11 * scale
        assert abs(float(wrap_angle_half(r[1] - r1[1]))) <= 1e-12
        np.testing.assert_allclose(JT @ JL[:, 2], 0.0, atol=1e-11 * scale)
        J = JT @ JL[:, :2]
        if J_ref is None:
            J_ref = J
        np.testing.assert_allclose(J, J_ref, atol=1e-11 * scale)


@given(T=poses(), Z=poses(), s=slides)
def test_line_chi2_ignores_where_the_targets_reference_point_lies(
    T: np.ndarray, Z: np.ndarray, s: float
) -> None:
    # χ² of the pairing with an uncertain target: the target's covariance moves with
    # its reference point, the residual's does not change.
    PT = bind_line_cov(T, _segment_cov(T, 0.0, 0.02**2, 0.003**2))
    PZ = _segment_cov(Z, 9.0, 0.01**2, 0.002**2)
    T2, J = _slide(T, s)
    PT2 = J @ PT @ J.T
    d2 = []
    for tt, pp in ((T, PT), (T2, PT2)):
        r, JT, _ = line_residual(tt, Z)
        S = JT @ pp @ JT.T + line_residual_cov(tt, Z, PZ)
        d2.append(float(r @ np.linalg.solve(S, r)))
    assert math.isclose(d2[0], d2[1], rel_tol=1e-6, abs_tol=1e-9)


@given(T=poses(), Z=poses(), along=st.floats(min_value=0.0, max_value=1e4))
def test_line_noise_ignores_the_along_line_pseudo_variance(
    T: np.ndarray, Z: np.ndarray, along: float
) -> None:
    tight = line_residual_cov(T, Z, _segment_cov(Z, 0.0, 0.01**2, 0.002**2))
    loose = line_residual_cov(T, Z, _segment_cov(Z, along, 0.01**2, 0.002**2))
    np.testing.assert_allclose(loose, tight, atol=1e-15)
    # Propagated through ∂r/∂Z of the bound covariance.
    _, _, JZ = line_residual(T, Z)
    Pb = bind_line_cov(Z, _segment_cov(Z, along, 0.01**2, 0.002**2))
    np.testing.assert_allclose(loose, JZ @ Pb @ JZ.T, atol=1e-15)


@given(Z=poses(), along=st.floats(min_value=0.0, max_value=1e4))
def test_line_noise_at_the_zero_residual_point_is_the_lateral_angle_block(
    Z: np.ndarray, along: float
) -> None:
    P = line_residual_cov(Z, Z, _segment_cov(Z, along, 0.01**2, 0.002**2))
    np.testing.assert_allclose(P, [[0.01**2, 1e-5], [1e-5, 0.002**2]], atol=1e-15)


@given(line=poses(), along=st.floats(min_value=0.0, max_value=1e4))
def test_bind_line_cov_removes_only_the_along_line_axis(line: np.ndarray, along: float) -> None:
    P = bind_line_cov(line, _segment_cov(line, along, 0.01**2, 0.002**2))
    u = np.array([math.cos(line[2]), math.sin(line[2]), 0.0])
    np.testing.assert_allclose(P @ u, 0.0, atol=1e-15)
    np.testing.assert_allclose(
        P, bind_line_cov(line, _segment_cov(line, 0.0, 1e-4, 4e-6)), atol=1e-15
    )


@given(X=poses(), L=poses(), z=poses())
def test_line_observation_jacobians(X: np.ndarray, L: np.ndarray, z: np.ndarray) -> None:
    r, JX, JL = line_observation(X, L, z)
    _not_perpendicular(r)
    np.testing.assert_allclose(r, line_residual(relative(X, L)[0], z)[0], atol=1e-12)
    np.testing.assert_allclose(
        JX,
        numerical_jacobian(lambda x: line_observation(x, L, z)[0], X, (1,)),
        atol=ATOL,
        rtol=RTOL,
    )
    np.testing.assert_allclose(
        JL,
        numerical_jacobian(lambda x: line_observation(X, x, z)[0], L, (1,)),
        atol=ATOL,
        rtol=RTOL,
    )


@given(X=poses(), L=poses(), along=coord, lat=small, ang=small)
def test_line_observation_is_the_world_midpoints_offset(
    X: np.ndarray, L: np.ndarray, along: float, lat: float, ang: float
) -> None:
    # The segment seen at X ⊕ z lies (lat, ang) off L at `along` metres along it.
    zw = compose(L, np.array([along, lat, ang]))
    z = relative(X, zw)[0]
    r, _, _ = line_observation(X, L, z)
    np.testing.assert_allclose(r, [lat, ang], atol=1e-9)
    np.testing.assert_allclose(
        line_observation_cov(X, L, z, np.diag([4.0, 1e-4, 4e-6])),
        line_residual_cov(relative(X, L)[0], z, np.diag([4.0, 1e-4, 4e-6])),
    )


# --------------------------------------------------------------------------- circle


@given(T=circles(), Z=circles())
def test_circle_residual_is_the_difference(T: np.ndarray, Z: np.ndarray) -> None:
    r, JT, JZ = circle_residual(T, Z)
    np.testing.assert_allclose(r, Z - T)
    np.testing.assert_allclose(JT, -np.eye(3))
    np.testing.assert_allclose(JZ, np.eye(3))
    cov = np.diag([1e-3, 2e-3, 5e-4])
    np.testing.assert_allclose(circle_residual_cov(T, Z, cov), cov)


@given(X=poses(), C=circles(), z=circles())
def test_circle_observation_jacobians(X: np.ndarray, C: np.ndarray, z: np.ndarray) -> None:
    r, JX, JC = circle_observation(X, C, z)
    pred = ft.express_circle_in(X, C)[0]
    np.testing.assert_allclose(r, z - pred, atol=1e-12)
    np.testing.assert_allclose(
        JX, numerical_jacobian(lambda x: circle_observation(x, C, z)[0], X), atol=ATOL, rtol=RTOL
    )
    np.testing.assert_allclose(
        JC, numerical_jacobian(lambda x: circle_observation(X, x, z)[0], C), atol=ATOL, rtol=RTOL
    )
    cov = np.diag([1e-3, 2e-3, 5e-4])
    np.testing.assert_allclose(circle_observation_cov(X, C, z, cov), cov)


# --------------------------------------------------------------------------- dispatch


@given(T=poses(), Z=poses(), X=poses())
def test_features_dispatch_to_the_models(T: np.ndarray, Z: np.ndarray, X: np.ndarray) -> None:
    for a, b in zip(pairing_residual(ft.FeatureKind.LINE, T, Z), line_residual(T, Z), strict=True):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(
        pairing_residual(ft.FeatureKind.LINE, T, Z, "target"),
        line_residual(T, Z, "target"),
        strict=True,
    ):
        np.testing.assert_array_equal(a, b)
    for a, b in zip(observe(ft.FeatureKind.LINE, Z, X, T), line_observation(X, T, Z), strict=True):
        np.testing.assert_array_equal(a, b)
    C, c = np.array([T[0], T[1], 0.4]), np.array([Z[0], Z[1], 0.5])
    for a, b in zip(
        observe(ft.FeatureKind.CIRCLE, c, X, C), circle_observation(X, C, c), strict=True
    ):
        np.testing.assert_array_equal(a, b)
    cov = _segment_cov(Z, 4.0, 1e-4, 4e-6)
    np.testing.assert_array_equal(
        pairing_cov(ft.FeatureKind.LINE, T, Z, cov), line_residual_cov(T, Z, cov)
    )


# --------------------------------------------------------------------------- fast copies


def _local_map(rng: np.random.Generator, theta: float) -> GaussianMap:
    """A robotcentric map: base, anchor, two lines, a circle, and two static known features."""
    m = GaussianMap()
    specs = [
        (ElementKind.POSE, Role.BASE, True),
        (ElementKind.POSE, Role.ANCHOR, True),
        (ElementKind.LINE, Role.FEATURE, True),
        (ElementKind.LINE, Role.FEATURE, True),
        (ElementKind.CIRCLE, Role.FEATURE, True),
        (ElementKind.LINE, Role.KNOWN, False),
        (ElementKind.CIRCLE, Role.KNOWN, False),
    ]
    n = len(specs)
    for kind, role, moving in specs:
        mean = np.array([*rng.uniform(-30, 30, 2), theta + rng.uniform(-1e-3, 1e-3)])
        if kind == ElementKind.CIRCLE:
            mean[2] = rng.uniform(0.1, 1.0)
        m.elements.append(Element(kind, role, moving=moving, track=len(m.elements)))
        m.mean = np.vstack([m.mean, mean[None, :]])
    A = rng.normal(0.0, 0.05, (3 * n, 3 * n))
    m.cov = A @ A.T + 1e-4 * np.eye(3 * n)
    m.wrap()
    m.bind_lines()
    return m


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), theta=angle)
def test_predict_all_targets_is_transform_feature(seed: int, theta: float) -> None:
    m = _local_map(np.random.default_rng(seed), theta)
    a = m.find(Role.ANCHOR)
    for kind, (targets, preds) in predict_all_targets(m, lambda e: True).items():
        for t, p in zip(targets, preds, strict=True):
            e = m.elements[t]
            want = m.mean[t]
            if e.role == Role.KNOWN:
                want = ft.transform_feature(kind.feature_kind(), m.mean[a], m.mean[t])[0]
            np.testing.assert_allclose(p, want, atol=1e-12, rtol=0.0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), theta=angle, u_theta=angle)
def test_predict_is_express_in_with_bound_odometry_noise(
    seed: int, theta: float, u_theta: float
) -> None:
    rng = np.random.default_rng(seed)
    m = _local_map(rng, theta)
    u = np.array([*rng.uniform(-1, 1, 2), u_theta])
    Q = np.diag([1e-3, 2e-3, 1e-4])
    n = len(m)
    want_mean = m.mean.copy()
    F = np.eye(3 * n)
    G = np.zeros((3 * n, 3))
    for i, e in enumerate(m.elements):
        if not e.moving:
            continue
        if e.kind == ElementKind.POSE:
            v, Ju, Jm = relative(u, m.mean[i])
        else:
            v, Ju, Jm = ft.express_in(e.kind.feature_kind(), u, m.mean[i])
        want_mean[i] = v
        F[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = Jm
        if e.kind == ElementKind.LINE:
            # The odometry noise must not put along-line variance on a bound line.
            Ju = bind_line_cov(v, np.eye(3)) @ Ju
        G[3 * i : 3 * i + 3] = Ju
    want_cov = F @ m.cov @ F.T + G @ Q @ G.T
    predict(m, u, Q)
    np.testing.assert_allclose(m.mean, want_mean, atol=1e-12, rtol=0.0)
    np.testing.assert_allclose(m.cov, want_cov, atol=1e-12, rtol=1e-10)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), theta=angle)
def test_bind_lines_is_bind_line_cov_on_every_line(seed: int, theta: float) -> None:
    m = _local_map(np.random.default_rng(seed), theta)
    A = np.random.default_rng(seed + 1).normal(0.0, 0.1, (3 * len(m), 3 * len(m)))
    m.cov = A @ A.T
    before = m.cov.copy()
    m.bind_lines()
    for i, e in enumerate(m.elements):
        b = before[3 * i : 3 * i + 3, 3 * i : 3 * i + 3]
        want = bind_line_cov(m.mean[i], b) if e.kind == ElementKind.LINE else b
        np.testing.assert_allclose(m.block(i), want, atol=1e-14, rtol=1e-12)
