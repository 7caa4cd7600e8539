"""Dataset odometry model and reflector-pole detection, on fabricated inputs."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from mapfuse_core.data.datasets import (
    CarGeometry,
    CarparkOptions,
    OdometryNoise,
    VictoriaParkOptions,
    dead_reckoning,
    detect_reflector_poles,
    integrate_odometry,
    rear_axle_speed,
)
from mapfuse_core.geometry.se2 import compose, inverse
from mapfuse_core.sim.vehicle import car_increment
from tests.jacobians import numerical_jacobian

# --------------------------------------------------------------------------- odometry model


def test_rear_axle_speed_corrects_the_left_encoder() -> None:
    g = CarGeometry()
    # Turning left (α > 0) the left wheel runs slower than the axle centre.
    vc = rear_axle_speed(np.array([2.0, 2.0, 2.0]), np.array([0.0, 0.3, -0.3]), g)
    assert vc[0] == 2.0
    assert vc[1] > 2.0 > vc[2]
    assert vc[1] == pytest.approx(2.0 / (1.0 - math.tan(0.3) * 0.76 / 2.83))
    with pytest.raises(ValueError, match="singular"):
        rear_axle_speed(np.array([1.0]), np.array([1.4]), g)


def test_straight_drive_gives_straight_increments() -> None:
    ct = np.arange(0.0, 2.0, 0.025)
    ts = np.array([0.0, 0.5, 1.0, 1.7])
    odo, cov = integrate_odometry(
        ct, np.full(ct.size, 2.0), np.zeros(ct.size), ts, CarGeometry(), OdometryNoise()
    )
    np.testing.assert_allclose(odo[0], 0.0)
    np.testing.assert_allclose(odo[1:], [[1.0, 0, 0], [1.0, 0, 0], [1.4, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(cov[0], 0.0)
    assert np.all(np.linalg.eigvalsh(cov[1:]) > 0.0)


def test_laser_odometry_is_the_rear_axle_motion_seen_from_the_laser() -> None:
    rng = np.random.default_rng(5)
    ct = np.sort(rng.uniform(0.0, 10.0, 300))
    ve, alpha = rng.uniform(0.5, 4.0, 300), rng.uniform(-0.5, 0.5, 300)
    ts = np.linspace(0.3, 9.8, 40)
    g = CarGeometry()
    rear_geom = dataclasses.replace(g, laser_forward_m=0.0, laser_left_m=0.0)
    laser, _ = integrate_odometry(ct, ve, alpha, ts, g, OdometryNoise())
    rear, _ = integrate_odometry(ct, ve, alpha, ts, rear_geom, OdometryNoise())
    laser_poses = dead_reckoning(laser, start=g.laser_mount)
    rear_poses = dead_reckoning(rear)
    for r, lp in zip(rear_poses, laser_poses, strict=True):
        np.testing.assert_allclose(compose(r, g.laser_mount), lp, atol=1e-9)


def test_controls_are_held_and_held_backwards_before_the_first_sample() -> None:
    ct = np.array([1.0, 2.0])
    # The car reports 1 m/s from t = 1, then 3 m/s; a step at t = 0.5 gets the first sample.
    odo, _ = integrate_odometry(
        ct,
        np.array([1.0, 3.0]),
        np.zeros(2),
        np.array([0.5, 1.5, 2.5, 4.0]),
        CarGeometry(),
        OdometryNoise(),
    )
    np.testing.assert_allclose(odo[1:, 0], [1.0, 0.5 * 1.0 + 0.5 * 3.0, 1.5 * 3.0])


@pytest.mark.parametrize("which", [0, 1, 2])
def test_odometry_covariance_is_the_propagated_control_error(which: int) -> None:
    """With one error source, cov = σ² g gᵀ with g the numerical derivative of the increment."""
    ct = np.arange(0.0, 3.0, 0.025)
    ve = 2.0 + 0.5 * np.sin(ct)
    alpha = 0.4 * np.sin(0.7 * ct)
    ts = np.array([0.2, 0.9, 1.3, 2.6])
    g = CarGeometry()
    sig = [0.0, 0.0, 0.0]
    sig[which] = 0.1
    noise = OdometryNoise(
        sigma_speed_mps=sig[0],
        sigma_speed_rel=sig[1],
        sigma_steer_rad=sig[2],
        floor_sigma_xy_m_per_sqrt_s=1e-12,
        floor_sigma_theta_rad_per_sqrt_s=1e-12,
    )
    _, cov = integrate_odometry(ct, ve, alpha, ts, g, noise)

    for k in (1, 2, 3):

        def inc(e: np.ndarray, k: int = k) -> np.ndarray:
            eps = float(e[0])
            v = ve + (eps if which == 0 else 0.0) + (eps * np.abs(ve) if which == 1 else 0.0)
            a = alpha + (eps if which == 2 else 0.0)
            return np.asarray(integrate_odometry(ct, v, a, ts, g, OdometryNoise())[0][k])

        gk = numerical_jacobian(inc, np.zeros(1), angle_rows=(2,))
        np.testing.assert_allclose(cov[k], 0.01 * gk @ gk.T, atol=1e-10, rtol=1e-5)


def test_slip_covariance_is_the_propagated_sideways_slip() -> None:
    """The slip term against its definition: each 25 ms control sample shifts the rear
    axle across its heading by ``e_i ~ N(0, σ²·|Δs_i|)``, so the laser increment's slip
    covariance is ``J·diag(σ²·|Δs_i|)·Jᵀ`` with ``J`` the numerical derivative of an
    independent composition of the samples with respect to the ``e_i``.  Tight steering
    makes the rear-axle speed (which the arc lengths use) 25 % above the encoder's."""
    g = CarGeometry()
    ct = np.arange(0.0, 1.0, 0.025)
    v, alpha = 3.0, 0.6
    ts = np.array([0.0, 0.3])
    quiet = {
        "sigma_speed_mps": 0.0,
        "sigma_speed_rel": 0.0,
        "sigma_steer_rad": 0.0,
        "floor_sigma_xy_m_per_sqrt_s": 1e-9,
        "floor_sigma_theta_rad_per_sqrt_s": 1e-9,
    }
    sigma = 0.04
    args = (ct, np.full(ct.size, v), np.full(ct.size, alpha), ts, g)
    odo, cov = integrate_odometry(*args, OdometryNoise(**quiet, sigma_slip_m_per_sqrt_m=sigma))
    _, cov0 = integrate_odometry(*args, OdometryNoise(**quiet))
    vc = float(rear_axle_speed(np.array([v]), np.array([alpha]), g)[0])
    assert vc > 1.2 * v
    delta, _ = car_increment(vc, alpha, 0.025, g.wheelbase_m)
    mount = g.laser_mount

    def laser_increment(slips: np.ndarray) -> np.ndarray:
        D = np.zeros(3)
        for e in slips:
            D = compose(compose(D, np.array([0.0, float(e), 0.0])), delta)
        return np.asarray(compose(compose(inverse(mount), D), mount))

    n = 12  # 0.3 s of 25 ms samples
    np.testing.assert_allclose(laser_increment(np.zeros(n)), odo[1], atol=1e-12)
    J = numerical_jacobian(laser_increment, np.zeros(n), angle_rows=(2,))
    expected = J @ np.diag(np.full(n, sigma**2 * vc * 0.025)) @ J.T
    np.testing.assert_allclose((cov - cov0)[1], expected, atol=1e-9)
    np.testing.assert_array_equal((cov - cov0)[:, 2], 0.0)  # slip does not turn the car
    # Standing still, nothing slips.
    still = (ct, np.zeros(ct.size), np.zeros(ct.size), ts, g)
    np.testing.assert_array_equal(
        integrate_odometry(*still, OdometryNoise(sigma_slip_m_per_sqrt_m=1.0))[1],
        integrate_odometry(*still, OdometryNoise())[1],
    )


def test_integrate_odometry_rejects_bad_inputs() -> None:
    g, n = CarGeometry(), OdometryNoise()
    ok = np.array([0.0, 1.0])
    with pytest.raises(ValueError, match="one length"):
        integrate_odometry(ok, np.ones(3), np.zeros(2), ok, g, n)
    with pytest.raises(ValueError, match="strictly increasing"):
        integrate_odometry(ok, np.ones(2), np.zeros(2), np.array([1.0, 1.0]), g, n)
    with pytest.raises(ValueError, match="strictly increasing"):
        integrate_odometry(np.array([1.0, 0.0]), np.ones(2), np.zeros(2), ok, g, n)


def test_options_are_validated() -> None:
    with pytest.raises(ValueError, match="pole_radius_m"):
        CarparkOptions(pole_radius_m=0.0)
    with pytest.raises(ValueError, match="cluster_max_beam_gap"):
        CarparkOptions(cluster_max_beam_gap=0)
    with pytest.raises(ValueError, match="sigma_speed_rel"):
        OdometryNoise(sigma_speed_rel=-0.1)
    with pytest.raises(ValueError, match="floor"):
        OdometryNoise(floor_sigma_xy_m_per_sqrt_s=0.0)
    with pytest.raises(ValueError, match="sigma_slip_m_per_sqrt_m"):
        OdometryNoise(sigma_slip_m_per_sqrt_m=-0.01)
    for bad in (math.nan, math.inf, True):
        with pytest.raises(ValueError, match="sigma_slip_m_per_sqrt_m"):
            OdometryNoise(sigma_slip_m_per_sqrt_m=bad)
    with pytest.raises(ValueError, match="wheelbase"):
        CarGeometry(wheelbase_m=math.nan)
    with pytest.raises(ValueError, match="sigma_range_m"):
        VictoriaParkOptions(sigma_range_m=-1.0)
    with pytest.raises(ValueError, match="speed_scale"):
        VictoriaParkOptions(speed_scale=0.0)
    with pytest.raises(ValueError, match="bearing_offset_rad"):
        VictoriaParkOptions(bearing_offset_rad=math.inf)


# --------------------------------------------------------------------------- reflector poles


def scan_with(returns: dict[int, tuple[float, int]]) -> tuple[np.ndarray, np.ndarray]:
    """A car-park scan: beam (0-based) → (range, intensity); other beams no return."""
    ranges = np.full(361, 81.91)
    intensity = np.zeros(361)
    for k, (r, i) in returns.items():
        ranges[k], intensity[k] = r, i
    return ranges, intensity


def test_pole_centre_is_behind_the_reflective_returns() -> None:
    opts = CarparkOptions()
    # Beams 180 and 181 (0° and 0.5°) flagged at 5 m; an unflagged wall elsewhere.
    ranges, intensity = scan_with({180: (5.0, 8192), 181: (5.02, 16384), 10: (3.0, 0)})
    poles, rejected = detect_reflector_poles(ranges, intensity, opts)
    assert rejected == {}
    assert len(poles) == 1
    circle, cov, n = poles[0]
    beta, rho = math.radians(0.25), 5.01 + opts.pole_radius_m
    np.testing.assert_allclose(circle, [rho * math.cos(beta), rho * math.sin(beta), 0.03])
    assert n == 2
    assert np.all(np.linalg.eigvalsh(cov) > 0.0)
    # Radial variance σρ² + σr²; the radius is uncorrelated with the centre.
    u = np.array([math.cos(beta), math.sin(beta)])
    assert u @ cov[:2, :2] @ u == pytest.approx(0.02**2 + 0.005**2)
    np.testing.assert_allclose(cov[2], [0.0, 0.0, 0.005**2])


def test_bearings_run_counter_clockwise_from_the_right() -> None:
    # Column 1 (beam 0) looks at −90° (right), column 361 at +90° (left).
    ranges, intensity = scan_with({0: (2.0, 8192), 360: (3.0, 8192)})
    poles, _ = detect_reflector_poles(ranges, intensity, CarparkOptions())
    right, left = (p[0] for p in poles)
    np.testing.assert_allclose(right[:2], [0.0, -2.03], atol=1e-12)
    np.testing.assert_allclose(left[:2], [0.0, 3.03], atol=1e-12)


def test_clusters_split_by_gap_and_wide_ones_are_rejected() -> None:
    opts = CarparkOptions()
    returns = {
        100: (4.0, 8192),
        102: (4.0, 8192),  # one missing beam: same pole
        110: (4.0, 8192),  # far in bearing: another pole
        200: (6.0, 8192),
        201: (7.0, 8192),  # 1 m behind: another object
        300: (40.0, 8192),  # beyond max_range_m
    }
    for k in range(250, 270):  # a 20-beam reflective stripe at 3 m: 0.5 m wide
        returns[k] = (3.0, 8192)
    poles, rejected = detect_reflector_poles(*scan_with(returns), opts)
    assert [p[2] for p in poles] == [2, 1, 1, 1]
    assert rejected == {"beyond_max_range": 1, "cluster_too_wide": 1}
