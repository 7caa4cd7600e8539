"""The ACFR car model and odometry: encoder correction, integration, noise propagation.

Both datasets come from the same kind of utility car (ACFR, University of Sydney): a
wheel encoder on the rear left wheel, a steering-angle sensor and a SICK laser mounted
ahead of the rear axle.

* The vehicle frame ``V`` has its origin at the centre of the rear axle, x forward,
  y to the left, angles counter-clockwise.  Positive steering turns left: the encoder on
  the *left* wheel then runs slower than the axle centre, hence the correction
  ``vc = ve / (1 − tan(α)·H/L)`` (:func:`rear_axle_speed`).
* The laser sits at ``(a, b) = (3.78, +0.5)`` m in ``V`` with the vehicle's heading.
  ``b`` is to the left: the ACFR model propagates the laser point with
  ``ẋ = vc cos φ − (vc/L) tan α (a sin φ + b cos φ)``, which is the velocity of the
  point ``(a, +b)``; ``docs/results/carpark.md`` gives the check against the car-park GPS.
* Odometry increments are those of the laser frame: it is the point the usual motion
  model propagates, the one compared with GPS, and the frame the features are given in.

Odometry between two steps integrates the controls with the exact-arc car model of
:func:`mapfuse_core.sim.vehicle.car_increment`, holding each control sample until the next
one (zero-order hold; before the first sample the first one is held, so a scan taken
before the odometry starts gets the first sample's motion).  Its covariance is the
first-order propagation of the control errors described by :class:`OdometryNoise`,
plus a small noise floor so that it is full rank.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from dataclasses import dataclass

import numpy as np

from mapfuse_core.data.datasets.common import check_finite
from mapfuse_core.geometry.se2 import FloatArray, compose, compose_jacobians, inverse, wrap_scalar
from mapfuse_core.sim.vehicle import car_increment


@dataclass(frozen=True)
class CarGeometry:
    """Geometry of the ACFR utility car (same for both datasets, ``docs/real-data.md``)."""

    wheelbase_m: float = 2.83
    """``L``: distance between the rear and the front axle (m)."""
    encoder_offset_m: float = 0.76
    """``H``: lateral offset of the rear-left wheel encoder from the centre line (m)."""
    laser_forward_m: float = 3.78
    """``a``: laser position ahead of the rear axle (m)."""
    laser_left_m: float = 0.5
    """``b``: laser position to the left of the centre line (m); see the module notes."""

    def __post_init__(self) -> None:
        check_finite("CarGeometry", "wheelbase_m", self.wheelbase_m, positive=True)
        check_finite("CarGeometry", "encoder_offset_m", self.encoder_offset_m, positive=False)
        for name in ("laser_forward_m", "laser_left_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"CarGeometry.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"CarGeometry.{name} must be finite, got {value}")

    @property
    def laser_mount(self) -> FloatArray:
        """Pose of the laser frame in the vehicle (rear-axle) frame, ``(a, b, 0)``."""
        return np.array([self.laser_forward_m, self.laser_left_m, 0.0])


@dataclass(frozen=True)
class OdometryNoise:
    """Errors of the dead-reckoning sensors, propagated into the odometry covariance.

    The errors of a wheel encoder and a steering sensor are not white at 40 Hz: wheel
    radius, tyre slip and steering calibration change slowly.  Treating each 25 ms sample
    as independent would average them away by ``√n`` within a scan interval and make the
    odometry overconfident, so the model is one error *per step*, common to all samples
    of that step: the encoder speed reads ``ve + ε_abs + ε_rel·|ve|`` and the steering
    ``α + ε_α``, with ``(ε_abs, ε_rel, ε_α)`` zero-mean, independent, and fresh at
    every step.  A floor of white motion noise, growing with the step's duration, makes
    the covariance full rank (control errors alone give a rank-2 covariance when driving
    straight: lateral displacement and heading both come from the steering).
    """

    sigma_speed_mps: float = 0.02
    """σ of ``ε_abs`` (m/s): the encoder's speed resolution (the car-park velocities
    move in steps of 0.0197 m/s), so that a slow car is not absurdly certain."""
    sigma_speed_rel: float = 0.05
    """σ of ``ε_rel`` (fraction of the speed): wheel radius and tyre slip, a few per
    cent for a car on grass or tarmac; 0.1 m/s at the car park's 2 m/s."""
    sigma_steer_rad: float = math.radians(1.0)
    """σ of ``ε_α`` (rad): steering-sensor calibration and the tyres' slip angles as they
    change the turn rate (sideways motion is :attr:`sigma_slip_m_per_sqrt_m`); 1°
    gives 0.15° of heading per car-park scan at 2 m/s."""
    floor_sigma_xy_m_per_sqrt_s: float = 0.005
    """Floor on x and y of the laser increment, σ per √s (about 2 mm per car-park scan)."""
    floor_sigma_theta_rad_per_sqrt_s: float = math.radians(0.1)
    """Floor on the heading increment, σ per √s (about 0.05° per car-park scan)."""
    steer_saturation_rad: float = math.inf
    """Steering readings with ``|α|`` at or above this are at the sensor's end stop: they
    say only that the wheels are turned at least that far.  Off (``inf``) by default."""
    sigma_steer_saturated_rad: float = math.radians(1.0)
    """σ of ``ε_α`` (rad) for a step holding a saturated steering reading."""
    sigma_slip_m_per_sqrt_m: float = 0.0
    """Sideways slip of the rear axle, σ per √m travelled (m/√m).  The kinematic model
    has the rear axle move along the car's heading; tyres under side load do not quite
    (slip angles), and the slip's effect on the laser is a lateral displacement that an
    EKF cannot put elsewhere when the heading is held by landmarks.  Modelled as a random
    walk across the direction of travel in distance (``σ²·|Δs|`` per control sample, the
    samples independent, unlike the control errors, which are held for a step), so it
    does not depend on the scan rate.  Not the simulation's per-step
    ``VehicleParams.slip_sigma``.  0 (off) by default; see
    :data:`VICTORIA_PARK_ODOMETRY_NOISE`."""

    def __post_init__(self) -> None:
        for name in (
            "sigma_speed_mps",
            "sigma_speed_rel",
            "sigma_steer_rad",
            "sigma_slip_m_per_sqrt_m",
        ):
            check_finite("OdometryNoise", name, getattr(self, name), positive=False)
        for name in ("floor_sigma_xy_m_per_sqrt_s", "floor_sigma_theta_rad_per_sqrt_s"):
            check_finite("OdometryNoise", name, getattr(self, name), positive=True)
        check_finite(
            "OdometryNoise",
            "sigma_steer_saturated_rad",
            self.sigma_steer_saturated_rad,
            positive=False,
        )
        sat = self.steer_saturation_rad
        if isinstance(sat, bool) or not isinstance(sat, int | float) or not sat > 0.0:
            raise ValueError(f"OdometryNoise.steer_saturation_rad must be > 0, got {sat!r}")

    @property
    def control_cov(self) -> FloatArray:
        """``diag(σ_abs², σ_rel², σ_α²)`` of the per-step control errors (3×3)."""
        return np.diag([self.sigma_speed_mps**2, self.sigma_speed_rel**2, self.sigma_steer_rad**2])

    @property
    def control_cov_saturated(self) -> FloatArray:
        """:attr:`control_cov` of a step whose steering reading hit the end stop."""
        return np.diag(
            [self.sigma_speed_mps**2, self.sigma_speed_rel**2, self.sigma_steer_saturated_rad**2]
        )

    def floor_cov(self, dt: float) -> FloatArray:
        """Noise floor of a step lasting ``dt`` seconds (3×3, in the laser frame)."""
        sxy, sth = self.floor_sigma_xy_m_per_sqrt_s, self.floor_sigma_theta_rad_per_sqrt_s
        return np.diag([sxy**2 * dt, sxy**2 * dt, sth**2 * dt])


def rear_axle_speed(
    encoder_speed: FloatArray, steering: FloatArray, geometry: CarGeometry
) -> FloatArray:
    """Speed of the rear-axle centre from the rear-left encoder: ``ve / (1 − tan(α)·H/L)``.

    Raises ``ValueError`` for a steering angle that makes the correction singular
    (a turn centred on the encoder wheel) or exceeds ``π/2``.
    """
    alpha = np.asarray(steering, dtype=np.float64)
    if np.any(np.abs(alpha) >= math.pi / 2.0):
        raise ValueError("steering angle must satisfy |α| < π/2")
    den = 1.0 - np.tan(alpha) * geometry.encoder_offset_m / geometry.wheelbase_m
    if np.any(den <= 0.1):
        i = int(np.argmin(den))
        raise ValueError(f"steering angle {alpha[i]} rad makes the encoder correction singular")
    return np.asarray(np.asarray(encoder_speed, dtype=np.float64) / den, dtype=np.float64)


def integrate_odometry(
    control_times: FloatArray,
    encoder_speed: FloatArray,
    steering: FloatArray,
    step_times: FloatArray,
    geometry: CarGeometry,
    noise: OdometryNoise,
) -> tuple[FloatArray, FloatArray]:
    """Laser-frame odometry increments and covariances between consecutive ``step_times``.

    ``encoder_speed`` (m/s, rear-left wheel) and ``steering`` (rad, positive left) are
    sampled at ``control_times`` and held until the next sample.  Row ``k ≥ 1`` is the
    increment ``x^{R_{k−1}}_{R_k}`` of the laser frame and its covariance (see
    :class:`OdometryNoise`); row 0 is zero.  Raises ``ValueError`` for inconsistent or
    non-increasing inputs.
    """
    ct = np.asarray(control_times, dtype=np.float64).reshape(-1)
    ve = np.asarray(encoder_speed, dtype=np.float64).reshape(-1)
    alpha = np.asarray(steering, dtype=np.float64).reshape(-1)
    ts = np.asarray(step_times, dtype=np.float64).reshape(-1)
    m = ct.shape[0]
    if m == 0 or ve.shape[0] != m or alpha.shape[0] != m:
        raise ValueError(
            f"control arrays must be non-empty and of one length, got {m}, "
            f"{ve.shape[0]}, {alpha.shape[0]}"
        )
    if ts.shape[0] == 0:
        raise ValueError("no step times")
    for name, arr in (("control_times", ct), ("step_times", ts)):
        if not np.all(np.isfinite(arr)) or np.any(np.diff(arr) <= 0.0):
            raise ValueError(f"{name} must be finite and strictly increasing")
    vc = rear_axle_speed(ve, alpha, geometry)
    L = geometry.wheelbase_m
    hl = geometry.encoder_offset_m / L
    # ∂vc/∂ve and ∂vc/∂α of the encoder correction, per sample.
    den = 1.0 - np.tan(alpha) * hl
    dvc_dve = 1.0 / den
    dvc_dalpha = ve * hl / (np.cos(alpha) ** 2 * den**2)
    ct_list = ct.tolist()
    vc_list, alpha_list = vc.tolist(), alpha.tolist()
    dvc_dve_list, dvc_da_list = dvc_dve.tolist(), dvc_dalpha.tolist()
    abs_ve_list = np.abs(ve).tolist()

    mount = geometry.laser_mount
    mount_inv = inverse(mount)
    Sigma_eps, Sigma_sat = noise.control_cov, noise.control_cov_saturated
    slip_var = noise.sigma_slip_m_per_sqrt_m**2
    saturated_list = (np.abs(alpha) >= noise.steer_saturation_rad).tolist()
    n = ts.shape[0]
    odometry = np.zeros((n, 3))
    odometry_cov = np.zeros((n, 3, 3))
    j = max(bisect_right(ct_list, float(ts[0])) - 1, 0)
    for k in range(1, n):
        t, t1 = float(ts[k - 1]), float(ts[k])
        # Rear-axle increment since step k−1, and its Jacobian w.r.t. (ε_abs, ε_rel, ε_α).
        x = y = th = 0.0
        # Rows of G as plain floats: this loop runs once per control sample (62k for
        # Victoria Park) and numpy's per-call overhead would dominate 3×3 arithmetic.
        g0 = [0.0, 0.0, 0.0]
        g1 = [0.0, 0.0, 0.0]
        g2 = [0.0, 0.0, 0.0]
        saturated = False
        # Slip covariance (x, y block) of the rear axle, accumulated along the path.
        lxx = lxy = lyy = 0.0
        while t < t1:
            saturated = saturated or saturated_list[j]
            t_next = ct_list[j + 1] if j + 1 < m else math.inf
            t_end = min(t_next, t1)
            delta, J_u = car_increment(vc_list[j], alpha_list[j], t_end - t, L)
            dx, dy, dth = delta.tolist()
            (jv0, ja0), (jv1, ja1), (jv2, ja2) = J_u.tolist()
            a_, r_, s_ = dvc_dve_list[j], dvc_dve_list[j] * abs_ve_list[j], dvc_da_list[j]
            # ∂δ/∂(ε_abs, ε_rel, ε_α), one row per component of δ.
            e0 = (jv0 * a_, jv0 * r_, jv0 * s_ + ja0)
            e1 = (jv1 * a_, jv1 * r_, jv1 * s_ + ja1)
            e2 = (jv2 * a_, jv2 * r_, jv2 * s_ + ja2)
            c, s = math.cos(th), math.sin(th)
            # Slip of this sample: σ²·|Δs| across the heading at its start, (−s, c).
            w = slip_var * abs(vc_list[j]) * (t_end - t)
            lxx, lxy, lyy = lxx + w * s * s, lxy - w * s * c, lyy + w * c * c
            # G ← J1⊕(D, δ)·G + J2⊕(D)·∂δ/∂ε  (composition D ⊕ δ, D the running increment)
            k0, k1 = -s * dx - c * dy, c * dx - s * dy
            for i in range(3):
                g0[i] += k0 * g2[i] + c * e0[i] - s * e1[i]
                g1[i] += k1 * g2[i] + s * e0[i] + c * e1[i]
                g2[i] += e2[i]
            x, y, th = x + c * dx - s * dy, y + s * dx + c * dy, th + dth
            t = t_end
            if t_end == t_next:
                j += 1
        G = np.array([g0, g1, g2])
        D = np.array([x, y, wrap_scalar(th)])
        cov_D = G @ (Sigma_sat if saturated else Sigma_eps) @ G.T
        cov_D[:2, :2] += np.array([[lxx, lxy], [lxy, lyy]])
        # Laser increment ⊖c ⊕ D ⊕ c: the same motion seen by the laser mounted at c.
        Dc, J1, _ = compose_jacobians(D, mount)
        inc, _, J2 = compose_jacobians(mount_inv, Dc)
        J = J2 @ J1
        cov = J @ cov_D @ J.T + noise.floor_cov(float(ts[k] - ts[k - 1]))
        odometry[k] = inc
        odometry_cov[k] = 0.5 * (cov + cov.T)
    return odometry, odometry_cov


def dead_reckoning(odometry: FloatArray, start: FloatArray | None = None) -> FloatArray:
    """Poses ``(N, 3)`` obtained by composing the increments from ``start`` (default origin)."""
    inc = np.asarray(odometry, dtype=np.float64)
    poses = np.zeros((inc.shape[0], 3))
    poses[0] = np.zeros(3) if start is None else np.asarray(start, dtype=np.float64)
    for k in range(1, inc.shape[0]):
        poses[k] = compose(poses[k - 1], inc[k])
    return poses
