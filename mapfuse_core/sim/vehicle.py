"""Car-like vehicle, its odometry and a pure-pursuit driver (``docs/method.md`` §3).

The paper gives only the control noise (Table 1: σv on the velocity, σφ on the
steering angle); the motion model is our *(choice)*: a kinematic bicycle whose
reference point is the centre of the rear axle, driven by ``u = (v, φ)``.  Over
one sampling period with constant controls the rear axle moves on a circular arc of
curvature ``κ = tan φ / L``, so the increment in the vehicle frame is exact:

* ``Δθ = v·dt·κ``
* ``(Δx, Δy) = v·dt · sinc(Δθ/2) · (cos(Δθ/2), sin(Δθ/2))`` (the chord of the arc)

which tends smoothly to the straight line ``(v·dt, 0, 0)`` when ``φ → 0``.

The true controls come from a pure-pursuit driver following waypoints at constant
speed (:func:`simulate_motion`) or from a given table of controls
(:func:`simulate_controls`); the noise below is the same for both.

Noise enters twice, as in a real car:

* **odometry** (what the estimator sees): the increment of the *noisy* controls
  ``car_increment(v + n_v, φ + n_φ)`` with covariance
  ``J_u·diag(σv², σφ²)·J_uᵀ + R(Δθ)·diag(slip²)·R(Δθ)ᵀ`` evaluated at the noisy
  controls, as a real system must (it does not know the true ones);
* **truth**: ``x_k = x_{k−1} ⊕ (car_increment(v, φ) ⊕ slip)``, ``slip ~ N(0, diag(slip²))``.

The slip term is our *(choice)*.  Control noise alone gives a rank-2 covariance in
practice (lateral displacement and heading both come from φ, ``Δy ≈ Δx·Δθ/2``), which a
factor graph cannot whiten; a small independent slip on the true motion makes the
odometry covariance full rank while keeping it honest, because exactly that slip is
added to the true motion and to the covariance.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, as_pose, compose, relative, wrap_angle
from mapfuse_core.sensor import MAX_ANGLE_SIGMA
from mapfuse_core.sim.limits import MAX_STEPS

__all__ = [
    "MotionResult",
    "VehicleParams",
    "car_increment",
    "odometry_covariance",
    "pure_pursuit_steer",
    "relative_increments",
    "simulate_controls",
    "simulate_motion",
]


@dataclass(frozen=True)
class VehicleParams:
    """Car geometry, sampling, control noise and driver settings.

    Defaults are the paper's (Sect. 4.2, Table 1) where it gives them, else our choices.
    """

    wheelbase_m: float = 2.5
    """Distance ``L`` between rear and front axle, metres (a small car)."""
    dt_s: float = 0.125
    """Sampling period in seconds: 8 Hz, one laser scan per step (paper)."""
    speed_mps: float = 2.0
    """Constant commanded speed: 0.25 m per step at 8 Hz (paper)."""
    sigma_v: float = 0.10
    """Standard deviation of the measured velocity, m/s (Table 1)."""
    sigma_phi: float = math.pi / 360.0
    """Standard deviation of the measured steering angle, rad (Table 1); with
    ``max_steer_rad + 8 σφ < π/2`` so that the measured angle stays below π/2."""
    max_steer_rad: float = 0.5
    """Steering limit ``|φ| ≤ max_steer_rad`` (< π/2); 0.5 rad gives a 4.6 m turning radius."""
    lookahead_m: float = 6.0
    """Pure-pursuit look-ahead distance along the path, metres."""
    slip_sigma: tuple[float, float, float] = (0.002, 0.002, 0.0002)
    """Per-step slip ``(σx m, σy m, σθ rad)`` on the true motion, added to the odometry
    covariance; ``σθ ≤ π``.

    Small next to the control noise at 2 m/s (σv·dt = 0.0125 m along track, about
    9e-4 rad of heading from σφ), so Table 1 still dominates, but well above the
    ~1e-4 m lateral spread the controls produce, so the covariance is well conditioned.
    """

    def __post_init__(self) -> None:
        positive = {
            "wheelbase_m": self.wheelbase_m,
            "dt_s": self.dt_s,
            "speed_mps": self.speed_mps,
            "sigma_v": self.sigma_v,
            "sigma_phi": self.sigma_phi,
            "max_steer_rad": self.max_steer_rad,
            "lookahead_m": self.lookahead_m,
        }
        for name, value in positive.items():
            _check_positive(name, value)
        if self.max_steer_rad >= math.pi / 2.0:
            raise ValueError(f"max_steer_rad must be < π/2, got {self.max_steer_rad}")
        # The measured steering φ + n_φ must stay below π/2 (the bicycle model's limit):
        # 8 σ leaves a chance below 1e-15 a step.
        if self.max_steer_rad + 8.0 * self.sigma_phi >= math.pi / 2.0:
            raise ValueError(
                f"sigma_phi = {self.sigma_phi:g} is too large for max_steer_rad = "
                f"{self.max_steer_rad:g}: max_steer_rad + 8 sigma_phi must be < π/2"
            )
        slip = tuple(self.slip_sigma)
        if len(slip) != 3:
            raise ValueError(f"slip_sigma must have 3 entries (σx, σy, σθ), got {len(slip)}")
        for name, value in zip(("σx", "σy", "σθ"), slip, strict=True):
            _check_positive(f"slip_sigma {name}", value)
        if slip[2] > MAX_ANGLE_SIGMA:
            raise ValueError(f"slip_sigma σθ must be <= π rad, got {slip[2]}")
        object.__setattr__(self, "slip_sigma", tuple(float(s) for s in slip))

    @property
    def step_length_m(self) -> float:
        """Distance travelled per step at the commanded speed."""
        return self.speed_mps * self.dt_s

    @property
    def slip_cov(self) -> FloatArray:
        """``diag(slip_sigma²)`` (3×3)."""
        return np.diag(np.square(np.asarray(self.slip_sigma, dtype=np.float64)))


def _check_positive(name: str, value: object) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ValueError(f"{name} must be a number, got {value!r}")
    if not math.isfinite(value) or value <= 0.0:
        raise ValueError(f"{name} must be positive and finite, got {value}")


# --------------------------------------------------------------------------- kinematics

# Below this |u| the closed forms lose digits to cancellation; the truncated series
# are exact to ~u⁶ ≈ 1e-12 relative there.
_SERIES_U = 1e-2


def _sinc_and_derivative(u: float) -> tuple[float, float]:
    """``sin(u)/u`` and its derivative."""
    if abs(u) < _SERIES_U:
        u2 = u * u
        return 1.0 - u2 / 6.0 + u2 * u2 / 120.0, u * (-1.0 / 3.0 + u2 / 30.0 - u2 * u2 / 840.0)
    s, c = math.sin(u), math.cos(u)
    return s / u, (u * c - s) / (u * u)


def _cosc_and_derivative(u: float) -> tuple[float, float]:
    """``(1 − cos u)/u`` and its derivative."""
    if abs(u) < _SERIES_U:
        u2 = u * u
        return u * (0.5 - u2 / 24.0 + u2 * u2 / 720.0), 0.5 - u2 / 8.0 + u2 * u2 / 144.0
    s, c = math.sin(u), math.cos(u)
    return (1.0 - c) / u, (u * s - (1.0 - c)) / (u * u)


def car_increment(v: float, phi: float, dt: float, L: float) -> tuple[FloatArray, FloatArray]:
    """Exact-arc pose increment of the rear-axle centre over ``dt`` with controls ``(v, φ)``.

    Returns ``delta = (Δx, Δy, Δθ)`` in the vehicle frame at the start of the step and
    ``J_u = ∂delta/∂(v, φ)`` (3×2).  With ``s = v·dt`` and ``u = Δθ = s·tan φ / L``:
    ``Δx = s·sin(u)/u``, ``Δy = s·(1 − cos u)/u`` (the arc's chord), continuous at u = 0.
    ``Δθ`` is not wrapped: it is the turned angle, and |Δθ| < π for any sane step.
    """
    if not (math.isfinite(v) and math.isfinite(phi)):
        raise ValueError(f"controls must be finite, got v={v}, phi={phi}")
    if abs(phi) >= math.pi / 2.0:
        raise ValueError(f"steering angle must satisfy |phi| < π/2, got {phi}")
    if not (dt > 0.0 and L > 0.0):
        raise ValueError(f"dt and L must be positive, got dt={dt}, L={L}")
    s = v * dt
    kappa = math.tan(phi) / L
    u = s * kappa
    f, df = _sinc_and_derivative(u)
    g, dg = _cosc_and_derivative(u)
    du_dv = dt * kappa
    du_dphi = s / (L * math.cos(phi) ** 2)
    delta = np.array([s * f, s * g, u])
    J_u = np.array(
        [
            [dt * f + s * df * du_dv, s * df * du_dphi],
            [dt * g + s * dg * du_dv, s * dg * du_dphi],
            [du_dv, du_dphi],
        ]
    )
    return delta, J_u


def odometry_covariance(delta: FloatArray, J_u: FloatArray, params: VehicleParams) -> FloatArray:
    """Covariance of an odometry increment ``delta`` whose control Jacobian is ``J_u``.

    ``J_u·diag(σv², σφ²)·J_uᵀ`` for the control noise, plus the slip, which the truth
    applies as ``increment ⊕ slip`` and therefore rotates by ``Δθ`` into the frame at
    the start of the step.
    """
    Sigma_u = np.diag([params.sigma_v**2, params.sigma_phi**2])
    c, s = math.cos(delta[2]), math.sin(delta[2])
    R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    cov = J_u @ Sigma_u @ J_u.T + R @ params.slip_cov @ R.T
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


# --------------------------------------------------------------------------- driver


@dataclass(frozen=True)
class _Path:
    """A polyline with cumulative arc length, for pure pursuit."""

    points: FloatArray
    """(K, 2) waypoints, consecutive duplicates removed."""
    cum: FloatArray
    """(K,) arc length at each waypoint."""

    @staticmethod
    def of(waypoints: FloatArray) -> _Path:
        wp = np.asarray(waypoints, dtype=np.float64)
        if wp.ndim != 2 or wp.shape[1] != 2 or wp.shape[0] < 2:
            raise ValueError(f"waypoints must have shape (K >= 2, 2), got {wp.shape}")
        if not np.all(np.isfinite(wp)):
            raise ValueError("waypoints have a non-finite entry")
        seg = np.hypot(*np.diff(wp, axis=0).T)
        keep = np.concatenate([[True], seg > 1e-9])
        wp = wp[keep]
        if wp.shape[0] < 2:
            raise ValueError("waypoints must contain at least two distinct points")
        cum = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(wp, axis=0).T))])
        return _Path(points=wp, cum=cum)

    def point_at(self, arc: float) -> FloatArray:
        """Point at arc length ``arc``; beyond either end, on the end segment extended."""
        i = int(np.clip(np.searchsorted(self.cum, arc, side="right") - 1, 0, len(self.cum) - 2))
        a, b = self.points[i], self.points[i + 1]
        t = (arc - self.cum[i]) / (self.cum[i + 1] - self.cum[i])
        return np.asarray(a + t * (b - a), dtype=np.float64)

    def project(self, p: FloatArray, arc_lo: float, arc_hi: float) -> float:
        """Arc length of the point of the path within ``[arc_lo, arc_hi]`` closest to ``p``.

        The window keeps the progress monotonic and local, so a loop that passes near
        itself (start and end of a closed trajectory) is not short-cut.
        """
        last = len(self.cum) - 2
        i0 = int(np.clip(np.searchsorted(self.cum, arc_lo, side="right") - 1, 0, last))
        i1 = min(int(np.searchsorted(self.cum, arc_hi, side="left")), len(self.cum) - 1)
        i1 = max(i1, i0 + 1)
        a = self.points[i0:i1]
        d = self.points[i0 + 1 : i1 + 1] - a
        L2 = np.einsum("ij,ij->i", d, d)
        t = np.clip(np.einsum("ij,ij->i", p - a, d) / L2, 0.0, 1.0)
        foot = a + t[:, None] * d
        j = int(np.argmin(np.hypot(*(foot - p).T)))
        arc = float(self.cum[i0 + j] + t[j] * math.sqrt(float(L2[j])))
        # Past the last waypoint the foot clamps to it; follow the extension instead.
        if i0 + j == last and t[j] >= 1.0:
            u = d[j] / math.sqrt(float(L2[j]))
            arc = float(self.cum[-1] + max(float(np.dot(p - self.points[-1], u)), 0.0))
        return min(max(arc, arc_lo), arc_hi)


def pure_pursuit_steer(pose: FloatArray, target: FloatArray, params: VehicleParams) -> float:
    """Pure-pursuit steering angle from ``pose`` (rear axle) towards ``target`` (x, y).

    The arc through the rear axle and the target has curvature ``2·sin(α)/d`` (α the
    target's bearing, d its distance); the bicycle follows it with ``φ = atan(L·κ)``,
    clipped to the steering limit.
    """
    dx, dy = target[0] - pose[0], target[1] - pose[1]
    d = math.hypot(dx, dy)
    if d < 1e-9:
        return 0.0
    alpha = float(wrap_angle(math.atan2(dy, dx) - pose[2]))
    phi = math.atan(params.wheelbase_m * 2.0 * math.sin(alpha) / d)
    return float(np.clip(phi, -params.max_steer_rad, params.max_steer_rad))


# --------------------------------------------------------------------------- simulation


# eq=False: the fields hold arrays, whose == is elementwise; compare by identity instead.
@dataclass(frozen=True, eq=False)
class MotionResult:
    """A simulated drive: truth, true controls and odometry, one row per step (read-only).

    Row ``k ≥ 1`` of :attr:`controls`, :attr:`odometry` and :attr:`odometry_cov`
    describes the motion from pose ``k − 1`` to pose ``k``; row 0 is zero.
    """

    true_poses: FloatArray
    """(N, 3) true vehicle (rear-axle) poses in ``W``; ``true_poses[0]`` is the start."""
    controls: FloatArray
    """(N, 2) true controls ``(v m/s, φ rad)``; row 0 zero."""
    odometry: FloatArray
    """(N, 3) noisy increments ``x^{R_{k−1}}_{R_k}`` in the vehicle frame; row 0 zero."""
    odometry_cov: FloatArray
    """(N, 3, 3) covariance of each odometry increment; row 0 zero."""

    @property
    def path_length_m(self) -> float:
        """Length of the true polyline through the poses."""
        return float(np.hypot(*np.diff(self.true_poses[:, :2], axis=0).T).sum())


def simulate_motion(
    start: FloatArray,
    waypoints: FloatArray,
    steps: int,
    params: VehicleParams,
    rng: np.random.Generator,
) -> MotionResult:
    """Drive ``steps`` poses from ``start`` along ``waypoints`` by pure pursuit at constant speed.

    The driver steers from the true pose (a human driver sees where the car is); the
    speed is constant.  Per step, one draw of the control noise ``(n_v, n_φ)`` and one
    of the slip, in that order, from ``rng``; the same generator state gives the same
    result.  After the last waypoint the driver follows the last segment extended.
    """
    x0 = as_pose(start, "start")
    if isinstance(steps, bool) or not isinstance(steps, int | np.integer) or steps < 2:
        raise ValueError(f"steps must be an integer >= 2, got {steps!r}")
    path = _Path.of(waypoints)
    v = params.speed_mps
    # Progress is searched only a little behind and ahead of the last value.
    arc = path.project(x0[:2], 0.0, min(path.cum[-1], 4.0 * params.lookahead_m))
    window = 4.0 * params.lookahead_m + 2.0 * params.step_length_m

    def driver(k: int, x: FloatArray) -> tuple[float, float]:
        nonlocal arc
        arc = path.project(x[:2], max(arc - params.step_length_m, 0.0), arc + window)
        return v, pure_pursuit_steer(x, path.point_at(arc + params.lookahead_m), params)

    return _drive(x0, int(steps), params, rng, driver)


def simulate_controls(
    start: FloatArray,
    controls: FloatArray,
    params: VehicleParams,
    rng: np.random.Generator,
) -> MotionResult:
    """Drive from ``start`` with given true controls, one row ``(v m/s, φ rad)`` per step.

    ``controls`` is (M, 2), M ≥ 1: row ``k`` moves pose ``k`` to pose ``k + 1``, so the
    result has M + 1 poses.  ``|φ|`` must not exceed ``params.max_steer_rad`` (the
    pure-pursuit driver never steers beyond it either); a negative ``v`` reverses.
    Noise is drawn exactly as in :func:`simulate_motion`.
    """
    x0 = as_pose(start, "start")
    u = np.asarray(controls, dtype=np.float64)
    if u.ndim != 2 or u.shape[1] != 2 or u.shape[0] < 1:
        raise ValueError(f"controls must have shape (M >= 1, 2), got {u.shape}")
    if not np.all(np.isfinite(u)):
        raise ValueError("controls have a non-finite entry")
    worst = int(np.argmax(np.abs(u[:, 1])))
    if abs(u[worst, 1]) > params.max_steer_rad:
        raise ValueError(
            f"controls[{worst}] steers {u[worst, 1]} rad, beyond the steering limit "
            f"max_steer_rad = {params.max_steer_rad}"
        )

    def table(k: int, x: FloatArray) -> tuple[float, float]:
        return float(u[k - 1, 0]), float(u[k - 1, 1])

    return _drive(x0, u.shape[0] + 1, params, rng, table)


def _drive(
    x0: FloatArray,
    n: int,
    params: VehicleParams,
    rng: np.random.Generator,
    control: Callable[[int, FloatArray], tuple[float, float]],
) -> MotionResult:
    """``n`` poses from ``x0``; ``control(k, x_{k−1})`` gives the true ``(v, φ)`` of step k."""
    if n > MAX_STEPS:
        raise ValueError(f"{n} poses is above the maximum of {MAX_STEPS:,} steps")
    dt, L = params.dt_s, params.wheelbase_m
    slip_sd = np.asarray(params.slip_sigma)
    noise_sd = np.array([params.sigma_v, params.sigma_phi])

    poses = np.zeros((n, 3))
    controls = np.zeros((n, 2))
    odometry = np.zeros((n, 3))
    odometry_cov = np.zeros((n, 3, 3))
    poses[0] = x0
    for k in range(1, n):
        x = poses[k - 1]
        v, phi = control(k, x)
        controls[k] = (v, phi)
        n_u = rng.normal(0.0, noise_sd)
        slip = rng.normal(0.0, slip_sd)
        true_inc, _ = car_increment(v, phi, dt, L)
        poses[k] = compose(x, compose(true_inc, slip))
        # Noisy steering may exceed the mechanical limit by a few σ; the model still holds.
        z, J_u = car_increment(v + float(n_u[0]), phi + float(n_u[1]), dt, L)
        odometry[k] = z
        odometry_cov[k] = odometry_covariance(z, J_u, params)
    for a in (poses, controls, odometry, odometry_cov):
        a.setflags(write=False)
    return MotionResult(
        true_poses=poses, controls=controls, odometry=odometry, odometry_cov=odometry_cov
    )


def relative_increments(true_poses: FloatArray) -> FloatArray:
    """True increments ``⊖x_{k−1} ⊕ x_k`` (row 0 zero), to compare with the odometry."""
    out = np.zeros_like(true_poses)
    for k in range(1, true_poses.shape[0]):
        out[k] = relative(true_poses[k - 1], true_poses[k])[0]
    return out
