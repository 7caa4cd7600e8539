"""SE(2) compounding, inversion and point transforms: values, identities, Jacobians."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from mapfuse_core.geometry import se2
from tests.jacobians import ATOL, RTOL, numerical_jacobian, poses


def pose_close(a: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> bool:
    return bool(
        np.allclose(a[:2], b[:2], atol=tol) and abs(float(se2.wrap_angle(a[2] - b[2]))) < tol
    )


@pytest.mark.parametrize(
    ("a", "expected"),
    [
        (0.0, 0.0),
        (math.pi, math.pi),
        (-math.pi, math.pi),
        (3 * math.pi, math.pi),
        (2 * math.pi, 0.0),
        (-0.5, -0.5),
        (math.pi + 0.1, -math.pi + 0.1),
    ],
)
def test_wrap_angle_range_and_pi_convention(a: float, expected: float) -> None:
    assert float(se2.wrap_angle(a)) == pytest.approx(expected, abs=1e-12)


def test_wrap_angle_half_is_modulo_pi() -> None:
    a = np.linspace(-10, 10, 2001)
    w = se2.wrap_angle_half(a)
    assert np.all(w > -math.pi / 2)
    assert np.all(w <= math.pi / 2)
    assert np.allclose(np.sin(2 * (w - a)), 0.0, atol=1e-9)


def test_compose_known_value() -> None:
    a = np.array([1.0, 2.0, math.pi / 2])
    b = np.array([3.0, 0.0, math.pi / 2])
    assert np.allclose(se2.compose(a, b), [1.0, 5.0, math.pi])


@given(poses())
def test_compose_with_inverse_is_identity(a: np.ndarray) -> None:
    assert pose_close(se2.compose(a, se2.inverse(a)), np.zeros(3))
    assert pose_close(se2.compose(se2.inverse(a), a), np.zeros(3))


@given(poses(), poses(), poses())
def test_compose_is_associative(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> None:
    lhs = se2.compose(se2.compose(a, b), c)
    rhs = se2.compose(a, se2.compose(b, c))
    assert pose_close(lhs, rhs, tol=1e-8)


@given(poses(), poses())
def test_relative_equals_inverse_compose(a: np.ndarray, b: np.ndarray) -> None:
    v, _, _ = se2.relative(a, b)
    assert pose_close(v, se2.compose(se2.inverse(a), b), tol=1e-9)


@given(poses(), poses())
def test_compose_jacobians(a: np.ndarray, b: np.ndarray) -> None:
    _, J1, J2 = se2.compose_jacobians(a, b)
    n1 = numerical_jacobian(lambda x: se2.compose(x, b), a, angle_rows=(2,))
    n2 = numerical_jacobian(lambda x: se2.compose(a, x), b, angle_rows=(2,))
    np.testing.assert_allclose(J1, n1, atol=ATOL, rtol=RTOL)
    np.testing.assert_allclose(J2, n2, atol=ATOL, rtol=RTOL)


@given(poses())
def test_inverse_jacobian(a: np.ndarray) -> None:
    _, J = se2.inverse_jacobian(a)
    np.testing.assert_allclose(
        J, numerical_jacobian(se2.inverse, a, angle_rows=(2,)), atol=ATOL, rtol=RTOL
    )


@given(poses(), poses())
def test_relative_jacobians(a: np.ndarray, b: np.ndarray) -> None:
    _, Ja, Jb = se2.relative(a, b)
    na = numerical_jacobian(lambda x: se2.relative(x, b)[0], a, angle_rows=(2,))
    nb = numerical_jacobian(lambda x: se2.relative(a, x)[0], b, angle_rows=(2,))
    np.testing.assert_allclose(Ja, na, atol=ATOL, rtol=RTOL)
    np.testing.assert_allclose(Jb, nb, atol=ATOL, rtol=RTOL)


@given(poses(), poses())
def test_transform_point_jacobians(a: np.ndarray, p3: np.ndarray) -> None:
    p = p3[:2]
    _, Ja, Jp = se2.transform_point_jacobians(a, p)
    np.testing.assert_allclose(
        Ja, numerical_jacobian(lambda x: se2.transform_point(x, p), a), atol=ATOL, rtol=RTOL
    )
    np.testing.assert_allclose(
        Jp, numerical_jacobian(lambda x: se2.transform_point(a, x), p), atol=ATOL, rtol=RTOL
    )


def test_as_pose_rejects_bad_input() -> None:
    with pytest.raises(ValueError, match="shape"):
        se2.as_pose([1.0, 2.0])
    with pytest.raises(ValueError, match="non-finite"):
        se2.as_pose([1.0, float("nan"), 0.0], name="start")


@given(st.floats(min_value=-50.0, max_value=50.0, allow_nan=False))
def test_scalar_wraps_match_vectorised(a: float) -> None:
    assert se2.wrap_scalar(a) == pytest.approx(float(se2.wrap_angle(a)), abs=1e-12)
    assert se2.wrap_scalar_half(a) == pytest.approx(float(se2.wrap_angle_half(a)), abs=1e-12)
    for edge in (math.pi, -math.pi, 3 * math.pi):
        assert se2.wrap_scalar(edge) == pytest.approx(math.pi)


def test_transform_point_moves_many_points_like_one() -> None:
    a = np.array([1.0, -2.0, 2.5])
    pts = np.random.default_rng(4).uniform(-10.0, 10.0, (7, 2))
    many = se2.transform_point(a, pts)
    assert many.shape == (7, 2)
    for p, q in zip(pts, many, strict=True):
        np.testing.assert_allclose(q, se2.transform_point(a, p), atol=1e-15)
    np.testing.assert_allclose(many, [se2.compose(a, [*p, 0.0])[:2] for p in pts], atol=1e-12)
