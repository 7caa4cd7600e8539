"""Line and circle models: conversions, frame changes, pairings and their Jacobians."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from mapfuse_core import models as md
from mapfuse_core.geometry import features as ft
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import compose, inverse, wrap_angle
from tests.jacobians import ATOL, RTOL, circles, numerical_jacobian, poses

KINDS = [FeatureKind.LINE, FeatureKind.CIRCLE]


def feature_of(kind: FeatureKind, p: np.ndarray) -> np.ndarray:
    if kind == FeatureKind.CIRCLE:
        return np.array([p[0], p[1], 0.5 + abs(p[2])])
    return p


def test_normal_form_round_trip_known_value() -> None:
    line = ft.normal_to_line(5.0, math.pi / 2)  # the line y = 5
    assert np.allclose(line, [0.0, 5.0, math.pi])
    rho_alpha, _ = ft.line_to_normal(line)
    assert np.allclose(rho_alpha, [5.0, math.pi / 2])


@given(poses())
def test_line_to_normal_round_trip(line: np.ndarray) -> None:
    (rho, alpha), _ = ft.line_to_normal(line)
    assume(rho > 1e-3)
    assert rho >= 0.0
    back = ft.normal_to_line(rho, alpha)
    # Same infinite line: zero pairing residual.
    r, _, _ = md.line_pairing(line, back)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)


@given(poses())
def test_line_to_normal_jacobian(line: np.ndarray) -> None:
    (rho, _), J = ft.line_to_normal(line)
    assume(rho > 1e-3)  # |ρ| is not differentiable at a line through the origin
    num = numerical_jacobian(lambda x: ft.line_to_normal(x)[0], line, angle_rows=(1,))
    np.testing.assert_allclose(J, num, atol=ATOL, rtol=RTOL)


@given(st.floats(0.0, 100.0), st.floats(-math.pi, math.pi), st.floats(-50.0, 50.0))
def test_line_from_normal_jacobian(rho: float, alpha: float, t: float) -> None:
    _, J = ft.line_from_normal(rho, alpha, t)
    num = numerical_jacobian(
        lambda x: ft.line_from_normal(x[0], x[1], x[2])[0], np.array([rho, alpha, t]), (2,)
    )
    np.testing.assert_allclose(J, num, atol=ATOL, rtol=RTOL)


@given(poses())
def test_canonical_line_points_y_axis_to_origin(line: np.ndarray) -> None:
    c = ft.canonical_line(line)
    r, _, _ = md.line_pairing(line, c)
    np.testing.assert_allclose(r, 0.0, atol=1e-9)
    lateral_of_origin = math.sin(c[2]) * c[0] - math.cos(c[2]) * c[1]
    assert lateral_of_origin >= -1e-9


def test_line_pairing_ignores_along_line_and_direction() -> None:
    l1 = np.array([0.0, 0.0, 0.3])
    along = np.array([7.0 * math.cos(0.3), 7.0 * math.sin(0.3), 0.3 + math.pi])
    r, _, _ = md.line_pairing(l1, along)
    np.testing.assert_allclose(r, 0.0, atol=1e-12)
    shifted = np.array([-0.2 * math.sin(0.3), 0.2 * math.cos(0.3), 0.3 + 0.01])
    r, _, _ = md.line_pairing(l1, shifted)
    np.testing.assert_allclose(r, [0.2, 0.01], atol=1e-12)


@given(poses(), poses())
def test_line_pairing_jacobians(l1: np.ndarray, l2: np.ndarray) -> None:
    r, J1, J2 = md.line_pairing(l1, l2)
    assume(abs(abs(r[1]) - math.pi / 2) > 1e-3)  # the modulo-π wrap is a jump there
    assert J1.shape == (2, 3)
    assert J2.shape == (2, 3)
    n1 = numerical_jacobian(lambda x: md.line_pairing(x, l2)[0], l1, angle_rows=(1,))
    n2 = numerical_jacobian(lambda x: md.line_pairing(l1, x)[0], l2, angle_rows=(1,))
    np.testing.assert_allclose(J1, n1, atol=ATOL, rtol=RTOL)
    np.testing.assert_allclose(J2, n2, atol=ATOL, rtol=RTOL)


@given(circles(), circles())
def test_circle_pairing_jacobians(c1: np.ndarray, c2: np.ndarray) -> None:
    r, J1, J2 = md.circle_pairing(c1, c2)
    np.testing.assert_allclose(r, c2 - c1)
    np.testing.assert_allclose(J1, numerical_jacobian(lambda x: md.circle_pairing(x, c2)[0], c1))
    np.testing.assert_allclose(J2, numerical_jacobian(lambda x: md.circle_pairing(c1, x)[0], c2))


@pytest.mark.parametrize("kind", KINDS)
@given(T=poses(), p=poses())
def test_transform_and_express_are_inverse(kind: FeatureKind, T: np.ndarray, p: np.ndarray) -> None:
    f = feature_of(kind, p)
    g, _, _ = ft.transform_feature(kind, T, f)
    back, _, _ = ft.express_in(kind, T, g)
    r, _, _ = md.pairing_residual(kind, f, back)
    np.testing.assert_allclose(r, 0.0, atol=1e-8)
    if kind == FeatureKind.LINE:
        np.testing.assert_allclose(g, compose(T, f)[:3], atol=1e-12)
        np.testing.assert_allclose(back[:2], compose(inverse(T), g)[:2], atol=1e-8)


@pytest.mark.parametrize("kind", KINDS)
@given(T=poses(), p=poses())
def test_transform_and_express_jacobians(kind: FeatureKind, T: np.ndarray, p: np.ndarray) -> None:
    f = feature_of(kind, p)
    rows = (2,) if kind == FeatureKind.LINE else ()
    for fn in (ft.transform_feature, ft.express_in):
        _, JT, Jf = fn(kind, T, f)
        nT = numerical_jacobian(lambda x, fn=fn: fn(kind, x, f)[0], T, angle_rows=rows)
        nf = numerical_jacobian(lambda x, fn=fn: fn(kind, T, x)[0], f, angle_rows=rows)
        np.testing.assert_allclose(JT, nT, atol=ATOL, rtol=RTOL)
        np.testing.assert_allclose(Jf, nf, atol=ATOL, rtol=RTOL)


@pytest.mark.parametrize("kind", KINDS)
@given(T=poses(), p=poses(), z=poses())
def test_observe_jacobians(kind: FeatureKind, T: np.ndarray, p: np.ndarray, z: np.ndarray) -> None:
    f = feature_of(kind, p)
    zf = feature_of(kind, z)
    r, JT, Jf = md.observe(kind, zf, T, f)
    assert r.shape == (ft.residual_dim(kind),)
    rows: tuple[int, ...] = ()
    if kind == FeatureKind.LINE:
        assume(abs(abs(r[1]) - math.pi / 2) > 1e-3)
        rows = (1,)
    nT = numerical_jacobian(lambda x: md.observe(kind, zf, x, f)[0], T, angle_rows=rows)
    nf = numerical_jacobian(lambda x: md.observe(kind, zf, T, x)[0], f, angle_rows=rows)
    np.testing.assert_allclose(JT, nT, atol=ATOL, rtol=RTOL)
    np.testing.assert_allclose(Jf, nf, atol=ATOL, rtol=RTOL)


@pytest.mark.parametrize("kind", KINDS)
@given(T=poses(), p=poses())
def test_observe_of_exact_measurement_is_zero(
    kind: FeatureKind, T: np.ndarray, p: np.ndarray
) -> None:
    f = feature_of(kind, p)
    z, _, _ = ft.express_in(kind, T, f)
    if kind == FeatureKind.LINE:
        z = ft.canonical_line(z)  # a measured line has its own direction convention
    r, _, _ = md.observe(kind, z, T, f)
    np.testing.assert_allclose(r, 0.0, atol=1e-8)


def test_line_angle_residual_near_pi_flip() -> None:
    # Two nearly antiparallel frames of one line: the angle residual is small, not ≈ π.
    l1 = np.array([0.0, 0.0, math.pi - 1e-4])
    l2 = np.array([3.0, 0.0, -math.pi + 1e-4 + math.pi])
    r, _, _ = md.line_pairing(l1, l2)
    assert abs(r[1]) < 1e-3
    assert float(wrap_angle(math.pi)) == pytest.approx(math.pi)
