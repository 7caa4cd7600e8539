"""Car-like vehicle: increment model and Jacobian, odometry honesty, driver, reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.stats import chi2

from mapfuse_core.geometry import se2
from mapfuse_core.sim.vehicle import (
    MotionResult,
    VehicleParams,
    car_increment,
    odometry_covariance,
    relative_increments,
    simulate_controls,
    simulate_motion,
)
from tests.jacobians import ATOL, RTOL, numerical_jacobian

MAX_STEER = VehicleParams().max_steer_rad

speeds = st.one_of(
    st.floats(min_value=-5.0, max_value=5.0, allow_nan=False),
    st.floats(min_value=-1e-6, max_value=1e-6, allow_nan=False),
)
steers = st.one_of(
    st.floats(min_value=-MAX_STEER, max_value=MAX_STEER, allow_nan=False),
    # near straight ahead, where the closed forms switch to series
    st.floats(min_value=-1e-3, max_value=1e-3, allow_nan=False),
    # near the steering limit (and a little past it, as noisy odometry can be)
    st.floats(min_value=MAX_STEER - 1e-3, max_value=MAX_STEER + 0.05, allow_nan=False),
    st.floats(min_value=-MAX_STEER - 0.05, max_value=-MAX_STEER + 1e-3, allow_nan=False),
)
periods = st.floats(min_value=0.01, max_value=1.0, allow_nan=False)
wheelbases = st.floats(min_value=1.0, max_value=5.0, allow_nan=False)


@given(speeds, steers, periods, wheelbases)
def test_car_increment_jacobian_matches_numerical(
    v: float, phi: float, dt: float, L: float
) -> None:
    _, J = car_increment(v, phi, dt, L)
    J_num = numerical_jacobian(
        lambda u: car_increment(float(u[0]), float(u[1]), dt, L)[0], np.array([v, phi])
    )
    np.testing.assert_allclose(J, J_num, atol=ATOL, rtol=RTOL)


@given(speeds, steers, periods, wheelbases)
def test_car_increment_lies_on_the_turning_circle(
    v: float, phi: float, dt: float, L: float
) -> None:
    d, _ = car_increment(v, phi, dt, L)
    assert d[2] == pytest.approx(v * dt * math.tan(phi) / L, abs=1e-12)
    # The rear axle moves on a circle of radius L / tan φ about (0, L / tan φ): its chord
    # has length 2R sin(Δθ/2) and direction Δθ/2.
    assert math.hypot(d[0], d[1]) <= abs(v * dt) + 1e-12
    if abs(d[2]) > 1e-9:
        assert math.atan2(d[1] * np.sign(v), d[0] * np.sign(v)) == pytest.approx(d[2] / 2, abs=1e-9)


def test_car_increment_known_values() -> None:
    d, _ = car_increment(2.0, 0.0, 0.125, 2.5)
    np.testing.assert_allclose(d, [0.25, 0.0, 0.0], atol=1e-15)
    # Quarter circle: R = L / tan φ, arc length s = R π/2.
    L, phi = 2.5, 0.4
    R = L / math.tan(phi)
    d, _ = car_increment(R * math.pi / 2, phi, 1.0, L)
    np.testing.assert_allclose(d, [R, R, math.pi / 2], atol=1e-12)


def test_car_increment_is_continuous_across_the_series_switch() -> None:
    # u = v dt tan φ / L crosses 1e-2 here; both branches must agree to rounding.
    L, dt, v = 2.5, 1.0, 1.0
    phi_switch = math.atan(1e-2 * L / (v * dt))
    lo, J_lo = car_increment(v, phi_switch * (1 - 1e-9), dt, L)
    hi, J_hi = car_increment(v, phi_switch * (1 + 1e-9), dt, L)
    np.testing.assert_allclose(lo, hi, atol=1e-10)
    np.testing.assert_allclose(J_lo, J_hi, atol=1e-8)


@pytest.mark.parametrize(
    ("v", "phi", "dt", "L"),
    [
        (1.0, math.pi / 2, 0.1, 2.5),
        (1.0, -2.0, 0.1, 2.5),
        (math.nan, 0.0, 0.1, 2.5),
        (1.0, math.inf, 0.1, 2.5),
        (1.0, 0.1, 0.0, 2.5),
        (1.0, 0.1, 0.1, -1.0),
    ],
)
def test_car_increment_rejects_bad_input(v: float, phi: float, dt: float, L: float) -> None:
    with pytest.raises(ValueError, match=r"phi|finite|positive"):
        car_increment(v, phi, dt, L)


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("wheelbase_m", 0.0),
        ("wheelbase_m", -2.5),
        ("wheelbase_m", math.nan),
        ("dt_s", math.inf),
        ("dt_s", 0.0),
        ("speed_mps", -2.0),
        ("sigma_v", 0.0),
        ("sigma_phi", -0.01),
        ("max_steer_rad", math.pi / 2),
        ("max_steer_rad", 0.0),
        ("lookahead_m", 0.0),
        ("slip_sigma", (0.002, 0.002, 0.0)),
        ("slip_sigma", (0.002, -0.002, 0.0002)),
        ("slip_sigma", (0.002, 0.002)),
        ("slip_sigma", (0.002, math.nan, 0.0002)),
        ("sigma_v", "0.1"),
        ("sigma_v", True),
    ],
)
def test_vehicle_params_reject_bad_values(field: str, value: object) -> None:
    with pytest.raises(ValueError, match=field.split("_")[0]):
        VehicleParams(**{field: value})  # type: ignore[arg-type]


def test_vehicle_params_defaults_are_the_papers() -> None:
    p = VehicleParams()
    assert p.dt_s == 0.125
    assert p.step_length_m == pytest.approx(0.25)
    assert p.sigma_v == 0.10
    assert p.sigma_phi == pytest.approx(math.pi / 360)
    assert np.linalg.eigvalsh(p.slip_cov).min() > 0.0


# --------------------------------------------------------------------------- simulation

# A rounded, irregular closed course: straights, tight and gentle turns, both directions.
COURSE = np.array(
    [[0, 0], [40, 0], [55, 15], [50, 40], [20, 35], [25, 20], [5, 25], [-10, 10], [0, 0]],
    dtype=float,
)
START = np.array([0.0, 0.0, 0.0])


def _drive(seed: int, steps: int = 1200, params: VehicleParams | None = None) -> MotionResult:
    return simulate_motion(
        START, COURSE, steps, params or VehicleParams(), np.random.default_rng(seed)
    )


def test_motion_result_layout() -> None:
    p = VehicleParams()
    m = _drive(1, steps=300)
    n = 300
    assert m.true_poses.shape == (n, 3)
    assert m.controls.shape == (n, 2)
    assert m.odometry.shape == (n, 3)
    assert m.odometry_cov.shape == (n, 3, 3)
    np.testing.assert_array_equal(m.true_poses[0], START)
    for a in (m.controls[0], m.odometry[0], m.odometry_cov[0]):
        assert not np.any(a)
    np.testing.assert_allclose(m.controls[1:, 0], p.speed_mps)
    assert np.all(np.abs(m.controls[1:, 1]) <= p.max_steer_rad)
    # Each true step is one increment of 0.25 m give or take the slip.
    steps = np.hypot(*np.diff(m.true_poses[:, :2], axis=0).T)
    np.testing.assert_allclose(steps, p.step_length_m, atol=0.02)
    assert np.all(np.abs(m.true_poses[:, 2]) <= math.pi)


def test_odometry_covariance_is_symmetric_positive_definite() -> None:
    m = _drive(2, steps=400)
    C = m.odometry_cov[1:]
    np.testing.assert_allclose(C, np.swapaxes(C, 1, 2), atol=0.0)
    assert np.linalg.eigvalsh(C).min() > 0.0


def test_odometry_covariance_matches_its_formula() -> None:
    p = VehicleParams()
    z, J = car_increment(2.1, 0.3, p.dt_s, p.wheelbase_m)
    expected = J @ np.diag([p.sigma_v**2, p.sigma_phi**2]) @ J.T + p.slip_cov  # σx = σy
    np.testing.assert_allclose(odometry_covariance(z, J, p), expected, atol=1e-15)


def test_seeded_runs_reproduce() -> None:
    a, b, c = _drive(7, 200), _drive(7, 200), _drive(8, 200)
    for name in ("true_poses", "controls", "odometry", "odometry_cov"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.odometry, c.odometry)
    assert not np.array_equal(a.true_poses, c.true_poses)


def test_odometry_nees_is_honest() -> None:
    """Odometry vs the true relative increment ``⊖x_{k−1} ⊕ x_k`` has NEES ≈ 3."""
    m = _drive(11, steps=4000)
    rel = relative_increments(m.true_poses)
    e = m.odometry[1:] - rel[1:]
    e[:, 2] = se2.wrap_angle(e[:, 2])
    nees = np.einsum("ki,kij,kj->k", e, np.linalg.inv(m.odometry_cov[1:]), e)
    n = nees.size
    # Consecutive steps are independent, so the sum is χ²(3n); 99 % two-sided interval.
    lo, hi = chi2.ppf([0.005, 0.995], 3 * n) / n
    assert lo <= nees.mean() <= hi, (nees.mean(), lo, hi)
    # Per component as well: each normalised error has unit variance.
    sd = np.sqrt(np.diagonal(m.odometry_cov[1:], axis1=1, axis2=2))
    z = e / sd
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.05)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=0.06)


def test_slip_is_the_gap_between_truth_and_noise_free_model() -> None:
    p = VehicleParams()
    m = _drive(5, steps=3000)
    rel = relative_increments(m.true_poses)
    slips = np.array(
        [
            se2.relative(car_increment(v, phi, p.dt_s, p.wheelbase_m)[0], rel[k])[0]
            for k, (v, phi) in enumerate(m.controls[1:], start=1)
        ]
    )
    np.testing.assert_allclose(slips.std(axis=0), p.slip_sigma, rtol=0.05)


def test_driver_follows_the_course_and_returns() -> None:
    m = _drive(3, steps=800)  # the course is ≈ 189 m: 756 steps, then its last leg extended
    P = m.true_poses
    dist_start = np.hypot(*P[:, :2].T)
    k_back = 600 + int(np.argmin(dist_start[600:]))
    # Back through the start, and never far from the course on the way: pure pursuit
    # (6 m look-ahead) cuts the 135° hairpin at (25, 20) by about 4 m, the rest by less.
    assert dist_start[k_back] < 0.5
    d = np.array([_distance_to_polyline(x[:2], COURSE) for x in P[: k_back + 1]])
    assert d.max() < 5.0
    assert np.median(d) < 0.5


def test_driver_converges_to_an_offset_line() -> None:
    start = np.array([0.0, 3.0, 0.3])
    m = simulate_motion(
        start, np.array([[0.0, 0.0], [200.0, 0.0]]), 400, VehicleParams(), np.random.default_rng(0)
    )
    assert abs(m.true_poses[-1, 1]) < 0.1
    assert abs(m.true_poses[-1, 2]) < 0.02


@pytest.mark.parametrize(
    ("waypoints", "steps"),
    [
        (np.array([[0.0, 0.0]]), 10),
        (np.array([[0.0, 0.0], [0.0, 0.0]]), 10),
        (np.array([[0.0, 0.0], [math.nan, 1.0]]), 10),
        (np.zeros((3, 3)), 10),
        (np.array([[0.0, 0.0], [10.0, 0.0]]), 1),
        (np.array([[0.0, 0.0], [10.0, 0.0]]), 2.5),
    ],
)
def test_simulate_motion_rejects_bad_input(waypoints: np.ndarray, steps: int) -> None:
    with pytest.raises(ValueError, match=r"waypoints|steps"):
        simulate_motion(START, waypoints, steps, VehicleParams(), np.random.default_rng(0))


def test_controls_replay_a_pure_pursuit_drive_exactly() -> None:
    """The same true controls and noise stream give the same drive, bit for bit."""
    course = np.array([[0.0, 0.0], [30.0, 0.0], [30.0, 30.0], [0.0, 30.0]])
    driven = simulate_motion(START, course, 300, VehicleParams(), np.random.default_rng(4))
    replay = simulate_controls(
        START, driven.controls[1:], VehicleParams(), np.random.default_rng(4)
    )
    for name in ("true_poses", "controls", "odometry", "odometry_cov"):
        assert getattr(replay, name).tobytes() == getattr(driven, name).tobytes(), name


def test_constant_controls_drive_the_turning_circle() -> None:
    """Constant (v, φ) with negligible slip: the rear axle stays on the circle of radius
    L / tan φ, turning v·dt·tan φ / L per step; a negative speed runs it backwards."""
    quiet = VehicleParams(slip_sigma=(1e-12, 1e-12, 1e-12))
    L, phi, n = quiet.wheelbase_m, 0.3, 200
    R = L / math.tan(phi)
    for v in (2.0, -1.0):
        m = simulate_controls(START, np.tile([v, phi], (n, 1)), quiet, np.random.default_rng(0))
        assert m.true_poses.shape == (n + 1, 3)
        np.testing.assert_array_equal(m.controls[1:], np.tile([v, phi], (n, 1)))
        centre = np.array([0.0, R])  # left of the start pose (0, 0, 0)
        radius = np.hypot(*(m.true_poses[:, :2] - centre).T)
        np.testing.assert_allclose(radius, R, atol=1e-8)
        turn = se2.wrap_angle(np.diff(m.true_poses[:, 2]))
        np.testing.assert_allclose(turn, v * quiet.dt_s * math.tan(phi) / L, atol=1e-10)


@pytest.mark.parametrize(
    ("controls", "match"),
    [
        (np.zeros((0, 2)), "shape"),
        (np.zeros((3, 3)), "shape"),
        (np.zeros(4), "shape"),
        (np.array([[2.0, 0.0], [math.inf, 0.0]]), "non-finite"),
        (np.array([[2.0, 0.0], [2.0, math.nan]]), "non-finite"),
        (np.array([[2.0, 0.1], [2.0, -0.6]]), r"controls\[1\].*steering limit"),
    ],
)
def test_simulate_controls_rejects_bad_input(controls: np.ndarray, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        simulate_controls(START, controls, VehicleParams(), np.random.default_rng(0))


def _distance_to_polyline(p: np.ndarray, poly: np.ndarray) -> float:
    a, b = poly[:-1], poly[1:]
    d = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, d) / np.einsum("ij,ij->i", d, d), 0.0, 1.0)
    return float(np.hypot(*(a + t[:, None] * d - p).T).min())
