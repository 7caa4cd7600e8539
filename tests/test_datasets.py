"""Real-dataset loaders: conventions checked against the data, odometry model, error paths.

The real-data tests use the ``data_dir`` fixture (skipped when the data is absent); the
rest run on small fabricated files.  Values quoted in comments, which justify the
tolerances, are those of the shared copies of the data with the default options.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.io
from scipy.optimize import least_squares

from mapfuse_core.datasets import (
    CARPARK_NAME,
    VICTORIA_PARK_NAME,
    VICTORIA_PARK_ODOMETRY_NOISE,
    CarGeometry,
    CarparkOptions,
    DatasetError,
    OdometryNoise,
    VictoriaParkOptions,
    dead_reckoning,
    detect_reflector_poles,
    integrate_odometry,
    load_carpark,
    load_victoria_park,
    rear_axle_speed,
)
from mapfuse_core.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.se2 import compose, compose_jacobians, inverse, relative, wrap_scalar
from mapfuse_core.vehicle import car_increment
from tests.jacobians import numerical_jacobian

# --------------------------------------------------------------------------- helpers


def rigid_fit(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation ``R`` and translation ``t`` minimising ``Σ‖R p + t − q‖²`` (Kabsch)."""
    mp, mq = P.mean(axis=0), Q.mean(axis=0)
    U, _, Vt = np.linalg.svd((P - mp).T @ (Q - mq))
    D = np.diag([1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, mq - R @ mp


def apply_rigid(R: np.ndarray, t: np.ndarray, poses: np.ndarray) -> np.ndarray:
    """Poses moved by the rigid transform ``(R, t)``."""
    out = poses.copy()
    out[:, :2] = poses[:, :2] @ R.T + t
    out[:, 2] = poses[:, 2] + math.atan2(R[1, 0], R[0, 0])
    return out


def gps_at(log: MeasurementLog, times: np.ndarray) -> np.ndarray:
    assert log.gps_times is not None
    assert log.gps_xy is not None
    return np.column_stack([np.interp(times, log.gps_times, log.gps_xy[:, i]) for i in range(2)])


def features_in_world(log: MeasurementLog, poses: np.ndarray) -> np.ndarray:
    """Centre of every feature in the frame of ``poses`` (one pose per step)."""
    x = poses[log.feat_step]
    c, s = np.cos(x[:, 2]), np.sin(x[:, 2])
    f = log.feat_params
    return np.column_stack(
        (x[:, 0] + c * f[:, 0] - s * f[:, 1], x[:, 1] + s * f[:, 0] + c * f[:, 1])
    )


def locally_aligned_poses(log: MeasurementLog, half_window_s: float) -> np.ndarray:
    """Dead reckoning re-aligned to GPS around every step (NaN where the car stands still).

    Removes the slow drift of dead reckoning so that what remains is the short-term
    odometry error, the GPS error and the sensor error.
    """
    dr = dead_reckoning(log.odometry)
    out = np.full_like(dr, np.nan)
    for k, t in enumerate(log.timestamps):
        m = np.abs(log.timestamps - t) <= half_window_s
        if np.ptp(dr[m, 0]) + np.ptp(dr[m, 1]) < 1.0:
            continue
        R, tr = rigid_fit(dr[m, :2], gps_at(log, log.timestamps[m]))
        out[k] = apply_rigid(R, tr, dr[k : k + 1])[0]
    return out


def pole_residuals(
    log: MeasurementLog, pose: np.ndarray, sl: slice, beacons: np.ndarray, gate_m: float
) -> list[tuple[int, int]]:
    """(feature index, beacon index) of the features of ``sl`` within ``gate_m`` of a beacon."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    f = log.feat_params[sl]
    centres = pose[:2] + f[:, :2] @ np.array([[c, s], [-s, c]])
    out = []
    for i, c in zip(range(sl.start, sl.stop), centres, strict=True):
        d = np.hypot(*(beacons - c).T)
        if d.min() < gate_m:
            out.append((int(i), int(np.argmin(d))))
    return out


def fit_pose(
    log: MeasurementLog, pairs: list[tuple[int, int]], beacons: np.ndarray, x0: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares laser pose from (feature, beacon) pairs; pose, covariance, residuals.

    Residuals are in range and bearing (m, rad); the weights include the survey σ.
    """
    known_var = float(log.known_map.covs[0, 0, 0])
    weights = [
        np.linalg.cholesky(np.linalg.inv(log.feat_cov[i][:2, :2] + known_var * np.eye(2))).T
        for i, _ in pairs
    ]

    def predicted(x: np.ndarray, j: int) -> np.ndarray:
        c, s = math.cos(x[2]), math.sin(x[2])
        d = beacons[j] - x[:2]
        return np.array([c * d[0] + s * d[1], -s * d[0] + c * d[1]])

    def fun(x: np.ndarray) -> np.ndarray:
        return np.concatenate(
            [
                W @ (predicted(x, j) - log.feat_params[i, :2])
                for (i, j), W in zip(pairs, weights, strict=True)
            ]
        )

    sol = least_squares(fun, x0)
    jac = np.asarray(sol.jac, dtype=np.float64)
    cov = np.linalg.inv(jac.T @ jac)
    res = []
    for i, j in pairs:
        p, f = predicted(sol.x, j), log.feat_params[i, :2]
        res.append(
            (
                math.hypot(*p) - math.hypot(*f),
                wrap_scalar(math.atan2(p[1], p[0]) - math.atan2(f[1], f[0])),
            )
        )
    return sol.x, cov, np.array(res)


def mad(v: np.ndarray) -> float:
    """Robust standard deviation (1.4826 × median absolute deviation)."""
    return float(1.4826 * np.median(np.abs(v - np.median(v))))


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


# --------------------------------------------------------------------------- car park (real)


@pytest.fixture(scope="module")
def carpark(data_dir: Path) -> MeasurementLog:
    return load_carpark(data_dir)


def test_carpark_structure(carpark: MeasurementLog, data_dir: Path) -> None:
    log = carpark
    raw = scipy.io.loadmat(str(data_dir / CARPARK_NAME / "data_set.mat"))
    assert log.scenario == CARPARK_NAME
    assert log.seed == -1
    assert log.n_steps == 586
    np.testing.assert_array_equal(log.timestamps, raw["TimeLaser"].ravel())
    assert np.all(np.linalg.eigvalsh(log.odometry_cov[1:]) > 0.0)
    assert np.all(log.feat_kind == FeatureKind.CIRCLE)
    # GPS-based reference labels: 903 of 911 poles, every beacon seen.
    labelled = log.feat_true_id >= 0
    assert labelled.mean() > 0.97
    assert set(log.feat_true_id[labelled].tolist()) == set(range(15))
    assert np.all(log.feat_params[:, 2] == 0.03)
    assert np.all(np.isnan(log.feat_extent))
    assert np.all(np.linalg.eigvalsh(log.feat_cov) > 0.0)
    # Detections: 911 poles in 586 scans (README's EKF associated 897 clusters).
    per_scan = np.bincount(log.feat_step, minlength=log.n_steps)
    assert 850 <= log.n_features <= 950
    assert 1.3 <= per_scan.mean() <= 1.8
    assert per_scan.max() <= 6
    assert np.all((log.feat_n_points >= 1) & (log.feat_n_points <= 10))
    km = log.known_map
    np.testing.assert_array_equal(km.ids, np.arange(15))
    assert np.all(km.kinds == FeatureKind.CIRCLE)
    beac = scipy.io.loadmat(str(data_dir / CARPARK_NAME / "beac_juan3.mat"))["estbeac"]
    np.testing.assert_array_equal(km.params[:, :2], beac)
    np.testing.assert_allclose(km.covs[0], np.diag([0.02**2, 0.02**2, 0.005**2]))
    assert log.gps_times is not None
    assert log.gps_xy is not None
    assert log.gps_times.shape == (626,)
    np.testing.assert_array_equal(log.gps_xy[:, 0], raw["GPSLon"].ravel())


def test_carpark_dead_reckoning_follows_gps(carpark: MeasurementLog) -> None:
    log = carpark
    dr = dead_reckoning(log.odometry)
    length = float(np.hypot(*np.diff(dr[:, :2], axis=0).T).sum())
    gps = gps_at(log, log.timestamps)
    gps_length = float(np.hypot(*np.diff(gps, axis=0).T).sum())
    # 226.8 m against 226.9 m of GPS (at the scan times).
    assert abs(length - gps_length) < 0.03 * gps_length
    m = log.timestamps < log.timestamps[0] + 20.0
    R, t = rigid_fit(dr[m, :2], gps[m])
    err = np.hypot(*(dr[m, :2] @ R.T + t - gps[m]).T)
    assert np.sqrt(np.mean(err**2)) < 0.3  # 0.13 m; 0.98 m with the laser on the right


def test_carpark_poles_project_onto_surveyed_beacons(carpark: MeasurementLog) -> None:
    """README check: the detected reflectors land on the surveyed beacons."""
    log = carpark
    beacons = log.known_map.params[:, :2]
    dr = dead_reckoning(log.odometry)
    # First 20 s: one rigid alignment of the dead reckoning to GPS.
    m = log.timestamps < log.timestamps[0] + 20.0
    R, t = rigid_fit(dr[m, :2], gps_at(log, log.timestamps[m]))
    world = features_in_world(log, apply_rigid(R, t, dr))
    first = log.feat_step < np.count_nonzero(m)
    d = np.hypot(*(world[first, None, :] - beacons[None]).T).min(axis=0)
    # 124 poles: median 0.23 m, max 0.50 m.
    assert first.sum() > 100
    assert np.median(d) < 0.35
    assert d.max() < 1.0
    # Whole run: dead reckoning re-aligned to GPS within ±2 s of every scan.
    local = locally_aligned_poses(log, 2.0)
    ok = ~np.isnan(local[log.feat_step, 0])
    world = features_in_world(log, np.nan_to_num(local))[ok]
    d = np.hypot(*(world[:, None, :] - beacons[None]).T).min(axis=0)
    # 677 poles (the others are seen while the car stands still): median 0.10 m, 95 %
    # within 0.33 m.
    assert ok.sum() > 600
    assert np.median(d) < 0.15
    assert np.quantile(d, 0.95) < 0.5


def carpark_fixes(log: MeasurementLog) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Per-scan least-squares poses from the surveyed beacons (scans seeing ≥ 3 of them)."""
    beacons = log.known_map.params[:, :2]
    local = locally_aligned_poses(log, 2.0)
    fixes = {}
    for k in range(log.n_steps):
        sl = log.feature_slice(k)
        if sl.stop - sl.start < 3 or np.isnan(local[k, 0]):
            continue
        pairs = pole_residuals(log, local[k], sl, beacons, 1.0)
        if len({j for _, j in pairs}) >= 3 and len(pairs) == len({j for _, j in pairs}):
            fixes[k] = fit_pose(log, pairs, beacons, local[k])
    return fixes


@pytest.fixture(scope="module")
def fixes(carpark: MeasurementLog) -> dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    return carpark_fixes(carpark)


def test_carpark_pole_noise_matches_the_fits(
    carpark: MeasurementLog, fixes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> None:
    """Residuals of beacon-only pose fits are of the size of σρ and σβ."""
    res = np.concatenate([f[2] for f in fixes.values()])
    # 64 scans, 193 poles: robust σ 1.3 cm and 0.22° (σρ = 2 cm, σβ = 0.35°, survey 2 cm;
    # the fit absorbs 3 of the 2n degrees of freedom).
    assert len(fixes) >= 40
    assert 0.005 < mad(res[:, 0]) < 0.03
    assert math.radians(0.15) < mad(res[:, 1]) < math.radians(0.6)


def test_carpark_odometry_covariance_is_consistent(
    carpark: MeasurementLog, fixes: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
) -> None:
    """NEES of composed odometry against beacon fixes 21–40 scans apart (4–8 s)."""
    log = carpark
    nees, lateral = [], []
    ks = sorted(fixes)
    for a in ks:
        for b in ks:
            if not 20 < b - a <= 40:
                continue
            x, P = np.zeros(3), np.zeros((3, 3))
            for q in range(a + 1, b + 1):
                x, J1, J2 = compose_jacobians(x, log.odometry[q])
                P = J1 @ P @ J1.T + J2 @ log.odometry_cov[q] @ J2.T
            r, Ja, Jb = relative(fixes[a][0], fixes[b][0])
            S = P + Ja @ fixes[a][1] @ Ja.T + Jb @ fixes[b][1] @ Jb.T
            e = x - r
            e[2] = wrap_scalar(float(e[2]))
            nees.append(float(e @ np.linalg.solve(S, e)))
            # Whitened in the order (θ, x, y): the last entry is the lateral error given
            # the heading and the forward one, what a sideways slip would inflate.
            idx = [2, 0, 1]
            lateral.append(
                float(np.linalg.solve(np.linalg.cholesky(S[np.ix_(idx, idx)]), e[idx])[2])
            )
    nees_arr = np.array(nees)
    # 165 pairs: mean 3.1 (3 expected), 2.4 % above χ²(3, 0.95).  With σα = 0.5° the
    # mean is 6.1 and 39 % exceed it.
    assert nees_arr.size > 50
    assert 1.5 < nees_arr.mean() < 5.0
    assert np.mean(nees_arr > 7.815) < 0.15
    # Mean square of the lateral part 1.19 without slip (1 expected; 0.38 with Victoria
    # Park's 4 cm/√m): the car park needs no slip term.
    assert 0.8 < float(np.mean(np.square(lateral))) < 2.0


# --------------------------------------------------------------------------- Victoria Park (real)


@pytest.fixture(scope="module")
def victoria(data_dir: Path) -> MeasurementLog:
    return load_victoria_park(data_dir)


def test_victoria_structure(victoria: MeasurementLog) -> None:
    log = victoria
    assert log.scenario == VICTORIA_PARK_NAME
    assert log.seed == -1
    # README: 52,974 detections in 7,230 scans; nothing filtered by default.
    assert log.n_steps == 7230
    assert log.n_features == 52974
    assert log.rejected == {}
    assert len(log.known_map) == 0
    assert np.all(np.linalg.eigvalsh(log.odometry_cov[1:]) > 0.0)
    assert np.all(np.linalg.eigvalsh(log.feat_cov) > 0.0)
    assert np.all(log.feat_kind == FeatureKind.CIRCLE)
    assert np.all(log.feat_params[:, 0] > -1e-9)  # 180° field of view ahead
    assert log.timestamps[-1] - log.timestamps[0] == pytest.approx(1548.4, abs=0.1)
    assert log.gps_times is not None
    assert log.gps_xy is not None
    assert log.gps_times.shape == (4466,)
    # GPS on the detections' clock: the first fix at t = 0, the last within the run.
    assert log.gps_times[0] == pytest.approx(0.0, abs=1e-9)
    assert log.timestamps[0] - 1.0 < log.gps_times[1] < log.timestamps[-1]


def test_victoria_first_detections_match_the_file(victoria: MeasurementLog, data_dir: Path) -> None:
    rows = np.loadtxt(data_dir / VICTORIA_PARK_NAME / "detections" / "measurements.dat", max_rows=5)
    t, rho, bearing, diam = rows.T
    opts = VictoriaParkOptions()
    assert np.all(victoria.feat_step[:5] == 0)
    assert victoria.timestamps[0] == pytest.approx(t[0] + opts.detection_time_offset_s)
    beta = bearing - math.pi / 2.0 + opts.bearing_offset_rad
    np.testing.assert_allclose(
        victoria.feat_params[:5],
        np.column_stack((rho * np.cos(beta), rho * np.sin(beta), diam / 2)),
    )


def test_victoria_trajectory_and_gps(victoria: MeasurementLog) -> None:
    log = victoria
    dr = dead_reckoning(log.odometry)
    length = float(np.hypot(*np.diff(dr[:, :2], axis=0).T).sum())
    assert 3000.0 < length < 5000.0  # 4.11 km in 26 min
    # The first minute against the (poor) GPS: median 1.5 m; 6.1 m with steering mirrored.
    m = log.timestamps < log.timestamps[0] + 60.0
    gps = gps_at(log, log.timestamps[m])
    R, t = rigid_fit(dr[m, :2], gps)
    assert np.median(np.hypot(*(dr[m, :2] @ R.T + t - gps).T)) < 2.5


def test_victoria_bearing_convention_keeps_trees_still(victoria: MeasurementLog) -> None:
    """Trees seen from consecutive scans land on each other only with β = bearing − π/2."""
    log = victoria
    dr = dead_reckoning(log.odometry)

    def median_nn(mirror: bool) -> float:
        f = log.feat_params.copy()
        if mirror:
            f[:, 1] *= -1.0
        mirrored = dataclasses.replace(log, feat_params=f)
        world = features_in_world(mirrored, dr)
        d = []
        for k in range(5, log.n_steps, 7):
            a, b = world[log.feature_slice(k)], world[log.feature_slice(k - 5)]
            if len(a) and len(b):
                d.append(np.hypot(*(a[:, None, :] - b[None]).T).min(axis=0))
        return float(np.median(np.concatenate(d)))

    # Five scans (1 s) apart: 0.30 m against 4.1 m mirrored.
    assert median_nn(False) < 0.5 < 2.0 < median_nn(True)


def _tracked_pair_distance(log: MeasurementLog, gap: int = 10) -> float:
    """Median distance (m) between detections of one trunk ``gap`` scans apart, both put
    in the world through the dead reckoning (pairs found scan to scan within 0.65 m)."""
    dr = dead_reckoning(log.odometry)
    world = features_in_world(log, dr)
    d = []
    for k in range(gap, log.n_steps, 3):
        a, b = world[log.feature_slice(k)], world[log.feature_slice(k - gap)]
        if len(a) and len(b):
            nn = np.hypot(*(a[:, None, :] - b[None]).T).min(axis=0)
            d.append(nn[nn < 0.65 + 0.05 * gap])
    return float(np.median(np.concatenate(d)))


def test_victoria_calibration_keeps_trees_stiller(victoria: MeasurementLog, data_dir: Path) -> None:
    """The tracking fit's steering zero, speed scale and latency (kept by default) bring
    the detections of a trunk two seconds apart closer together than the raw data; its
    laser yaw would bring them closer still, which is the sideways motion the default
    odometry takes as slip instead (``docs/victoria-park-calibration.md``)."""
    raw = load_victoria_park(
        data_dir,
        options=VictoriaParkOptions(
            bearing_offset_rad=0.0,
            steering_offset_rad=0.0,
            speed_scale=1.0,
            detection_time_offset_s=0.0,
        ),
    )
    yawed = load_victoria_park(data_dir, options=VictoriaParkOptions(bearing_offset_rad=-0.017))
    calibrated = _tracked_pair_distance(victoria)
    # Measured: 0.202 m by default, 0.300 m raw, 0.168 m with the −0.017 rad yaw.
    assert calibrated < 0.75 * _tracked_pair_distance(raw)
    assert _tracked_pair_distance(yawed) < 0.9 * calibrated
    np.testing.assert_allclose(raw.feat_params[:, 2], victoria.feat_params[:, 2])  # radii untouched
    assert raw.n_features == victoria.n_features


def test_victoria_odometry_has_the_sideways_slip(victoria: MeasurementLog, data_dir: Path) -> None:
    """The default log's odometry carries VICTORIA_PARK_ODOMETRY_NOISE's slip: across the
    direction of travel, σ²·|Δs| more variance per step than without it."""
    assert VictoriaParkOptions().odometry_noise == VICTORIA_PARK_ODOMETRY_NOISE
    plain = load_victoria_park(
        data_dir, options=VictoriaParkOptions(odometry_noise=OdometryNoise())
    )
    np.testing.assert_array_equal(plain.odometry, victoria.odometry)
    d = np.hypot(victoria.odometry[:, 0], victoria.odometry[:, 1])
    moving = d > 0.3
    extra = victoria.odometry_cov[moving, 1, 1] - plain.odometry_cov[moving, 1, 1]
    expected = VICTORIA_PARK_ODOMETRY_NOISE.sigma_slip_m_per_sqrt_m**2 * d[moving]
    # The laser sits 3.78 m ahead of the rear axle: in turns the slip's direction and the
    # travelled distance differ a little from the laser's; straight, they are the same.
    np.testing.assert_allclose(np.median(extra / expected), 1.0, rtol=0.05)
    np.testing.assert_allclose(
        victoria.odometry_cov[moving, 2, 2], plain.odometry_cov[moving, 2, 2], rtol=1e-9
    )


def test_victoria_filters_are_counted(data_dir: Path) -> None:
    log = load_victoria_park(
        data_dir, options=VictoriaParkOptions(max_range_m=30.0, min_diameter_m=0.1)
    )
    rows = np.loadtxt(data_dir / VICTORIA_PARK_NAME / "detections" / "measurements.dat")
    far = rows[:, 1] > 30.0
    small = (rows[:, 3] < 0.1) & ~far
    assert log.rejected == {"diameter_too_small": int(small.sum()), "range_too_far": int(far.sum())}
    assert log.n_features == rows.shape[0] - far.sum() - small.sum()
    assert log.n_steps == 7230  # steps are the scans, whatever is filtered


# --------------------------------------------------------------------------- error paths


def carpark_arrays(n_scans: int = 4, n_dr: int = 40, n_gps: int = 10) -> dict[str, Any]:
    """A tiny, valid car-park data set: the car drives straight at 2 m/s past one pole."""
    t_dr = 10.0 + 0.025 * np.arange(n_dr)
    laser = np.full((n_scans, 361), 81.91)
    intensity = np.zeros((n_scans, 361), dtype=np.uint16)
    laser[:, 270] = 4.0  # a pole 45° to the left
    intensity[:, 270] = 8192
    return {
        "TimeLaser": (10.1 + 0.2 * np.arange(n_scans))[None, :],
        "Laser": laser,
        "Intensity": intensity,
        "Time_VS": t_dr[None, :],
        "Velocity": np.full((1, n_dr), 2.0),
        "Steering": np.zeros((1, n_dr)),
        "TimeGPS": (10.0 + 0.2 * np.arange(n_gps))[None, :],
        "GPSLon": np.arange(n_gps, dtype=float)[None, :],
        "GPSLat": np.zeros((1, n_gps)),
    }


def write_carpark(root: Path, arrays: dict[str, Any], beacons: Any = None) -> Path:
    folder = root / CARPARK_NAME
    folder.mkdir(parents=True, exist_ok=True)
    scipy.io.savemat(str(folder / "data_set.mat"), arrays)
    scipy.io.savemat(
        str(folder / "beac_juan3.mat"),
        {"estbeac": np.array([[1.0, 2.0], [3.0, 4.0]]) if beacons is None else beacons},
    )
    return root


def test_fabricated_carpark_loads(tmp_path: Path) -> None:
    log = load_carpark(write_carpark(tmp_path, carpark_arrays()), known_sigma_m=0.05)
    assert log.n_steps == 4
    assert log.n_features == 4
    np.testing.assert_allclose(log.odometry[1:], [[0.4, 0.0, 0.0]] * 3, atol=1e-12)
    r = 4.03 / math.sqrt(2.0)
    np.testing.assert_allclose(log.feat_params, [[r, r, 0.03]] * 4, atol=1e-12)
    np.testing.assert_allclose(log.known_map.covs[:, 0, 0], 0.05**2)


def _del(name: str) -> Callable[[dict[str, Any]], None]:
    def edit(a: dict[str, Any]) -> None:
        del a[name]

    return edit


def _set(name: str, value: Any) -> Callable[[dict[str, Any]], None]:
    def edit(a: dict[str, Any]) -> None:
        a[name] = value

    return edit


def _nan_at(name: str, index: tuple[int, int]) -> Callable[[dict[str, Any]], None]:
    def edit(a: dict[str, Any]) -> None:
        arr = np.array(a[name], dtype=float)
        arr[index] = np.nan
        a[name] = arr

    return edit


@pytest.mark.parametrize(
    ("edit", "message"),
    [
        (_del("Intensity"), "missing variable 'Intensity'"),
        (_del("TimeGPS"), "missing variable 'TimeGPS'"),
        (_set("Laser", np.full((4, 360), 5.0)), r"'Laser' has shape \(4, 360\), expected 4×361"),
        (_set("Laser", np.full((3, 361), 5.0)), r"'Laser' has shape \(3, 361\), expected 4×361"),
        (_set("Steering", np.zeros((1, 39))), "'Steering' has 39 values, expected 40"),
        (
            _set("GPSLat", np.zeros((2, 10))),
            r"'GPSLat' has shape \(2, 10\), expected a non-empty vector",
        ),
        (_nan_at("Velocity", (0, 3)), r"'Velocity' has a non-finite value \(nan\)"),
        (_nan_at("Laser", (1, 20)), r"'Laser' has a non-finite value \(nan\) at index \(1, 20\)"),
        (
            _set("TimeLaser", np.array([[10.1, 10.3, 10.3, 10.5]])),
            "'TimeLaser' must be strictly increasing",
        ),
        (_set("Laser", np.zeros((4, 361))), "'Laser' has a range <= 0"),
        (_set("Steering", np.full((1, 40), 1.5)), "dead reckoning unusable"),
        (_set("Velocity", np.array(["fast"])), "'Velocity' is not a real numeric array"),
    ],
)
def test_carpark_malformed_data_set(
    tmp_path: Path, edit: Callable[[dict[str, Any]], None], message: str
) -> None:
    arrays = carpark_arrays()
    edit(arrays)
    root = write_carpark(tmp_path, arrays)
    with pytest.raises(DatasetError, match=message) as info:
        load_carpark(root)
    assert "data_set.mat" in str(info.value)


@pytest.mark.parametrize(
    ("beacons", "message"),
    [
        (np.zeros((15, 3)), r"'estbeac' has shape \(15, 3\), expected N×2"),
        (np.array([[1.0, np.nan]]), "'estbeac' has a non-finite value"),
        (np.zeros((0, 2)), "'estbeac'"),
    ],
)
def test_carpark_malformed_beacons(tmp_path: Path, beacons: np.ndarray, message: str) -> None:
    root = write_carpark(tmp_path, carpark_arrays(), beacons=beacons)
    with pytest.raises(DatasetError, match=message) as info:
        load_carpark(root)
    assert "beac_juan3.mat" in str(info.value)


def test_carpark_missing_and_damaged_files(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"data_set\.mat: no such file"):
        load_carpark(tmp_path)
    root = write_carpark(tmp_path, carpark_arrays())
    (root / CARPARK_NAME / "beac_juan3.mat").unlink()
    with pytest.raises(DatasetError, match=r"beac_juan3\.mat: no such file"):
        load_carpark(root)
    (root / CARPARK_NAME / "beac_juan3.mat").write_bytes(b"not a MATLAB file at all")
    with pytest.raises(DatasetError, match=r"beac_juan3\.mat: cannot be read as a MATLAB file"):
        load_carpark(root)
    scipy.io.savemat(str(root / CARPARK_NAME / "beac_juan3.mat"), {"other": np.zeros((2, 2))})
    with pytest.raises(DatasetError, match=r"beac_juan3\.mat: missing variable 'estbeac'"):
        load_carpark(root)


def write_victoria(
    root: Path,
    measurements: str | None = None,
    inputs: str | None = None,
    gps: dict[str, Any] | None = None,
) -> Path:
    """A tiny Victoria Park folder: three scans, straight drive at 1 m/s."""
    det = root / VICTORIA_PARK_NAME / "detections"
    det.mkdir(parents=True, exist_ok=True)
    if measurements is None:
        measurements = (
            "1.0 10.0 1.5707963 0.4\n1.0 5.0 0.7853982 0.2\n1.2 9.8 1.5707963 0.4\n"
            "1.4 9.6 1.5707963 0.4\n"
        )
    if inputs is None:
        inputs = "".join(f"{0.9 + 0.025 * i:.3f} 1.0 0.0\n" for i in range(30))
    (det / "measurements.dat").write_text(measurements)
    (det / "inputs.dat").write_text(inputs)
    if gps is None:
        gps = {
            "timeGps": np.array([[20967, 21967, 22167]], dtype=np.int32),
            "Lo_m": np.array([[0.0, 1.0, 1.2]]),
            "La_m": np.zeros((1, 3)),
        }
    scipy.io.savemat(str(root / VICTORIA_PARK_NAME / "aa3_gpsx.mat"), gps)
    return root


RAW_VICTORIA = VictoriaParkOptions(
    bearing_offset_rad=0.0, steering_offset_rad=0.0, speed_scale=1.0, detection_time_offset_s=0.0
)
"""No calibration: the files' values as they are."""


def test_fabricated_victoria_loads(tmp_path: Path) -> None:
    log = load_victoria_park(write_victoria(tmp_path), options=RAW_VICTORIA)
    assert log.n_steps == 3
    assert log.n_features == 4
    np.testing.assert_array_equal(log.feat_step, [0, 0, 1, 2])
    np.testing.assert_allclose(log.odometry[1:], [[0.2, 0.0, 0.0]] * 2, atol=1e-12)
    np.testing.assert_allclose(log.feat_params[0], [10.0, 0.0, 0.2], atol=1e-6)
    np.testing.assert_allclose(
        log.feat_params[1], [5 / math.sqrt(2), -5 / math.sqrt(2), 0.1], atol=1e-6
    )
    assert log.gps_times is not None
    np.testing.assert_allclose(log.gps_times, [0.0, 1.0, 1.2], atol=1e-9)


def test_fabricated_victoria_calibration_is_applied(tmp_path: Path) -> None:
    opts = VictoriaParkOptions(
        bearing_offset_rad=0.1,
        steering_offset_rad=0.0,
        speed_scale=1.5,
        detection_time_offset_s=-0.05,
    )
    log = load_victoria_park(write_victoria(tmp_path), options=opts)
    np.testing.assert_allclose(log.timestamps, [0.95, 1.15, 1.35], atol=1e-12)
    np.testing.assert_allclose(log.odometry[1:], [[0.3, 0.0, 0.0]] * 2, atol=1e-12)
    np.testing.assert_allclose(
        log.feat_params[0], [10 * math.cos(0.1), 10 * math.sin(0.1), 0.2], atol=1e-6
    )
    assert log.gps_times is not None  # GPS stays on the dead-reckoning clock
    np.testing.assert_allclose(log.gps_times, [0.0, 1.0, 1.2], atol=1e-9)
    turning = load_victoria_park(
        write_victoria(tmp_path), options=dataclasses.replace(RAW_VICTORIA, steering_offset_rad=0.1)
    )
    assert turning.odometry[1, 2] > 0.0  # positive steering offset turns left


@pytest.mark.parametrize(
    ("kwargs", "file", "message"),
    [
        ({"measurements": "1.0 10.0 1.5\n"}, "measurements.dat", "3 columns, expected 4"),
        ({"measurements": "1.0 10.0 1.5 nan\n"}, "measurements.dat", "non-finite value"),
        ({"measurements": "1.0 ten 1.5 0.3\n"}, "measurements.dat", "not a numeric table"),
        ({"measurements": ""}, "measurements.dat", "no rows"),
        ({"measurements": "1.0 10.0 1.5 0.0\n"}, "measurements.dat", "a diameter is <= 0"),
        ({"measurements": "1.0 10.0 4.0 0.3\n"}, "measurements.dat", "outside 0..π"),
        (
            {"measurements": "1.2 10.0 1.5 0.3\n1.0 10.0 1.5 0.3\n"},
            "measurements.dat",
            "non-decreasing",
        ),
        ({"inputs": "1.0 1.0\n"}, "inputs.dat", "2 columns, expected 3"),
        ({"inputs": "1.0 1.0 0.0\n1.0 1.0 0.0\n"}, "inputs.dat", "strictly increasing"),
        (
            {"gps": {"timeGps": np.zeros((1, 3)), "Lo_m": np.zeros((1, 3))}},
            "aa3_gpsx.mat",
            "missing variable 'La_m'",
        ),
        (
            {
                "gps": {
                    "timeGps": np.zeros((1, 3)),
                    "Lo_m": np.zeros((1, 2)),
                    "La_m": np.zeros((1, 3)),
                }
            },
            "aa3_gpsx.mat",
            "'Lo_m' has 2 values, expected 3",
        ),
    ],
)
def test_victoria_malformed_files(
    tmp_path: Path, kwargs: dict[str, Any], file: str, message: str
) -> None:
    root = write_victoria(tmp_path, **kwargs)
    with pytest.raises(DatasetError, match=message) as info:
        load_victoria_park(root)
    assert file in str(info.value)


def test_victoria_missing_files(tmp_path: Path) -> None:
    with pytest.raises(DatasetError, match=r"measurements\.dat: no such file"):
        load_victoria_park(tmp_path)
    root = write_victoria(tmp_path)
    (root / VICTORIA_PARK_NAME / "aa3_gpsx.mat").unlink()
    with pytest.raises(DatasetError, match=r"aa3_gpsx\.mat: no such file"):
        load_victoria_park(root)
