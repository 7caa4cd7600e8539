"""GTSAM factors of the mapfuse measurement models (docs/method.md §7, docs/method.md).

Every residual is a model of :mod:`mapfuse_core.models` (the EKF's own); this module
only chooses the landmark variables, chains the Jacobians and converts them to GTSAM's
tangent conventions.  The residual functions themselves are in :mod:`mapfuse_graph.residuals`
and re-exported here.  The *callbacks* of the observation factors (see "Closed-form
callbacks" below) evaluate the same functions in closed form, and the tests hold
them equal to the models.

Variables
---------
* **Pose** ``gtsam.Pose2`` ``(x, y, θ)``.  GTSAM retracts a Pose2 in its body frame,
  ``X ⊕ Exp(δ)``, whose derivative at ``δ = 0`` is ``blockdiag(R(θ), 1)``: a Jacobian
  with respect to the raw ``(x, y, θ)`` becomes ``J_abs · blockdiag(R(θ), 1)``
  (:func:`to_body`).
* **Line landmark** a 2-vector ``(ρ, α)``, the *signed* normal form: the points ``p``
  with ``p · (cos α, sin α) = ρ``.  ``ρ`` may be negative, so a line through the
  origin of its frame is a regular point of the parametrisation (the ``ρ ≥ 0`` form
  flips ``α`` by π there).  It has exactly the two real degrees of freedom of a
  line: no along-line coordinate, hence no gauge freedom and no need for the biased
  huge-σ ``BetweenFactorPose2`` trick.  Retraction is plain addition; ``α`` is never
  wrapped in the variable (residual angles are wrapped modulo π by the model).
  SPmap ``(x, y, θ)`` ↔ ``(ρ, α)``: ``α = θ − π/2``, ``ρ = x sin θ − y cos θ``
  (:func:`line_to_rho_alpha`); back with :func:`mapfuse_core.geometry.features.line_from_normal`.
* **Circle landmark** a 3-vector ``(x, y, r)``, retraction by addition.
* **Known feature** the same representations, in ``Wknown``.
* **Anchor** ``gtsam.Pose2`` ``A = x^Wglobal_Wknown``.

All vector variables are stored as dynamic ``gtsam`` Vectors (``Values.insert`` of a
numpy array) and read with ``Values.atVector``.

Factors
-------
* :func:`line_factor` (pose, line): ``line_observation(X, L(ρ, α), z)``, the offset of
  the observed segment's midpoint ``X ⊕ z_xy`` from the landmark line and the angle
  between them (:func:`line_observation_error`).
* :func:`circle_factor` (pose, circle): ``circle_observation(X, C, z)``;
  :func:`circle_centre_factor` (pose, centre) its first two rows, for a circle held as
  a centre and a separate radius variable (``GraphOptions.split_circles``).
* :func:`line_tie_factor`, :func:`circle_tie_factor` (anchor, landmark, known): the
  graph form of the paper's eq. 20, ``pairing(L, A ⊕ K) = 0``.
* :func:`known_line_prior_factor` (known line): ``line_residual(K(ρ, α), K_surveyed)``.

The measurement noise is the model's noise at the zero-residual point,
``line_residual_cov(z, z, Σz)`` (:func:`residual_noise_cov`): for a line the 2×2
(lateral, angle) block of ``Σz`` in the observed line's own frame, so the along-line
pseudo-variance never enters.

Closed-form callbacks
---------------------
The line and circle observation factors are most of the graph and GTSAM calls a
Python callback for each of them on every linearisation.  Going through the models
(``line_from_normal``, ``line_observation``, ``to_body``: about 20 small numpy arrays
and several matrix products per call) costs several times more per call than the same
numbers computed from the five scalars ``(x, y, θ, ρ, α)`` (``benchmarks/bench_graph.py``,
docs/method.md).  So :func:`line_factor` and :func:`circle_factor` hand GTSAM the
closed forms of :func:`line_observation_error` and :func:`circle_observation_error`
with the pose Jacobian already in the body tangent.  They are not a second model: the
tests (``test_*_factor_is_the_shared_model``) check on hypothesis-generated inputs,
θ and α near ±π included, that residuals and Jacobians equal the model functions
chained through :func:`to_body` to ~1e-12; change the model first, then these.

Jacobian shape guard
--------------------
A wrongly shaped Jacobian handed to GTSAM segfaults or silently corrupts the
system.  With ``MAPFUSE_CHECK_JACOBIANS=1`` in the environment, or after
:func:`set_jacobian_checks` ``(True)``, every callback checks the residual and each
Jacobian before giving them to GTSAM and raises :class:`JacobianShapeError` instead.
The tests turn it on; it adds a small cost to every call, so it is off by default.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence

import gtsam
import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, wrap_scalar_half
from mapfuse_core.models import pairing_cov
from mapfuse_graph.residuals import (
    circle_observation_error,
    circle_tie_error,
    known_line_prior_cov,
    known_line_prior_error,
    landmark_from_observation,
    line_observation_error,
    line_observation_residual,
    line_tie_error,
    line_to_rho_alpha,
    pose_of,
    rho_alpha_along,
    to_body,
    to_spmap_feature,
)

__all__ = [
    "JacobianShapeError",
    "circle_centre_factor",
    "circle_factor",
    "circle_observation_error",
    "circle_tie_error",
    "circle_tie_factor",
    "custom_factor",
    "jacobian_checks_enabled",
    "known_line_prior_cov",
    "known_line_prior_error",
    "known_line_prior_factor",
    "landmark_from_observation",
    "line_factor",
    "line_observation_error",
    "line_observation_residual",
    "line_tie_error",
    "line_tie_factor",
    "line_to_rho_alpha",
    "make_noise",
    "observation_factor",
    "observation_noise",
    "pose_of",
    "residual_noise_cov",
    "rho_alpha_along",
    "set_jacobian_checks",
    "to_body",
    "to_spmap_feature",
]

_ENV_FLAG = "MAPFUSE_CHECK_JACOBIANS"


class JacobianShapeError(ValueError):
    """A factor callback produced a residual or Jacobian GTSAM cannot take."""


class _Checks:
    """Mutable switch of the shape guard (a module-level bool cannot be rebound by tests)."""

    enabled: bool = os.environ.get(_ENV_FLAG, "").strip().lower() in ("1", "true", "yes", "on")


def set_jacobian_checks(enabled: bool) -> None:
    """Turn the residual/Jacobian shape guard of every callback on or off."""
    _Checks.enabled = bool(enabled)


def jacobian_checks_enabled() -> bool:
    """Whether the shape guard is on."""
    return _Checks.enabled


def _check(name: str, r: object, Js: Sequence[object], dims: Sequence[int]) -> None:
    if not (isinstance(r, np.ndarray) and r.ndim == 1 and r.dtype == np.float64):
        raise JacobianShapeError(f"{name}: residual must be a 1-D float64 array, got {r!r}")
    m = r.shape[0]
    if not np.all(np.isfinite(r)):
        raise JacobianShapeError(f"{name}: non-finite residual {r.tolist()}")
    if len(Js) != len(dims):
        raise JacobianShapeError(f"{name}: {len(Js)} Jacobians for {len(dims)} keys")
    for i, (J, d) in enumerate(zip(Js, dims, strict=True)):
        if not isinstance(J, np.ndarray) or J.shape != (m, d):
            shape = J.shape if isinstance(J, np.ndarray) else type(J).__name__
            raise JacobianShapeError(
                f"{name}: Jacobian {i} has shape {shape}, expected ({m}, {d}) "
                f"(residual dimension × tangent dimension of key {i})"
            )
        if not np.all(np.isfinite(J)):
            raise JacobianShapeError(f"{name}: Jacobian {i} has a non-finite entry")


def known_line_prior_factor(key: int, known: FloatArray, cov: FloatArray) -> gtsam.CustomFactor:
    """Prior factor of a known wall's ``(ρ, α)`` variable (:func:`known_line_prior_error`).

    One per known wall, so not on the hot path: it goes through :func:`custom_factor`.
    """
    known = np.asarray(known, dtype=float).copy()
    if known.shape != (3,) or not np.all(np.isfinite(known)):
        raise ValueError(f"known line must be 3 finite numbers (x, y, θ), got {known!r}")

    def error(values: gtsam.Values, keys: Sequence[int]) -> tuple[FloatArray, list[FloatArray]]:
        r, J = known_line_prior_error(values.atVector(keys[0]), known)
        return r, [J]

    noise = make_noise(known_line_prior_cov(known, cov))
    return custom_factor(noise, [key], (2,), error, name="known_line_prior")


# --------------------------------------------------------------------------- noise


def residual_noise_cov(kind: FeatureKind, z: FloatArray, cov: FloatArray) -> FloatArray:
    """The model's noise of observation ``z`` (covariance ``cov``) at the zero-residual point.

    ``pairing_cov(kind, z, z, cov)``: for a line the 2×2 (lateral, angle) block of ``Σ``
    in the line's own frame, for a circle ``Σ``.  A GTSAM noise model is fixed when
    the factor is made, so it is taken where the residual is zero.
    """
    return pairing_cov(kind, z, z, cov)


def _robust(spec: str | None, base: gtsam.noiseModel.Base) -> gtsam.noiseModel.Base:
    if spec is None:
        return base
    name, _, arg = spec.partition(":")
    name = name.strip().lower()
    try:
        k = float(arg) if arg else (1.345 if name == "huber" else 2.3849)
    except ValueError:
        raise ValueError(f"robust kernel parameter in {spec!r} is not a number") from None
    if not (math.isfinite(k) and k > 0):
        raise ValueError(f"robust kernel parameter must be > 0, got {spec!r}")
    est: gtsam.noiseModel.mEstimator.Base
    if name == "huber":
        est = gtsam.noiseModel.mEstimator.Huber.Create(k)
    elif name == "cauchy":
        est = gtsam.noiseModel.mEstimator.Cauchy.Create(k)
    else:
        raise ValueError(f"unknown robust kernel {spec!r}; use 'huber[:k]' or 'cauchy[:k]'")
    return gtsam.noiseModel.Robust.Create(est, base)


def make_noise(
    cov: FloatArray, robust: str | None = None, check: bool = True
) -> gtsam.noiseModel.Base:
    """Gaussian noise model of covariance ``cov`` (checked positive definite), maybe robust.

    ``robust`` is ``None``, ``"huber"``, ``"cauchy"`` or ``"huber:k"`` / ``"cauchy:k"``
    (k in units of σ; defaults 1.345 and 2.3849, the 95 %-efficiency constants).
    ``check=False`` skips the positive-definiteness test for input validated earlier
    (GTSAM itself would abort on a non-positive-definite covariance).
    """
    cov = np.asarray(cov, dtype=float)
    if not check:
        return _robust(robust, gtsam.noiseModel.Gaussian.Covariance(cov))
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1] or not np.all(np.isfinite(cov)):
        raise ValueError(f"noise covariance must be a finite square matrix, got {cov!r}")
    if np.abs(cov - cov.T).max() > 1e-9 * max(np.abs(cov).max(), 1e-300):
        raise ValueError(f"noise covariance is not symmetric: {cov.tolist()}")
    w = np.linalg.eigvalsh(cov)
    if w.min() <= 1e-14 * max(w.max(), 1e-300) or w.min() <= 0.0:
        raise ValueError(f"noise covariance is not positive definite (eigenvalues {w.tolist()})")
    return _robust(robust, gtsam.noiseModel.Gaussian.Covariance(cov))


def observation_noise(
    kind: FeatureKind,
    z: FloatArray,
    cov: FloatArray,
    robust: str | None = None,
    check: bool = True,
) -> gtsam.noiseModel.Base:
    """Noise model of an observation factor: :func:`residual_noise_cov`, maybe robust."""
    return make_noise(residual_noise_cov(kind, z, cov), robust, check)


# --------------------------------------------------------------------------- factors


def custom_factor(
    noise: gtsam.noiseModel.Base,
    keys: Sequence[int],
    dims: Sequence[int],
    error: Callable[[gtsam.Values, Sequence[int]], tuple[FloatArray, Sequence[FloatArray]]],
    name: str = "factor",
) -> gtsam.CustomFactor:
    """A CustomFactor from ``error(values, keys) -> (r, [J_i in each key's tangent])``.

    Generic (slower) wrapper with the shape guard, for factors that are not on the hot
    path and for testing the guard itself.
    """
    dims = tuple(int(d) for d in dims)

    def cb(
        this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None
    ) -> FloatArray:
        r, Js = error(values, this.keys())
        if _Checks.enabled:
            _check(name, r, Js, dims)
        if H is not None:
            for i, J in enumerate(Js):
                H[i] = J
        return r

    return gtsam.CustomFactor(noise, list(keys), cb)


def _line_cb(z: FloatArray) -> Callable[..., FloatArray]:
    """Callback of :func:`line_factor`: :func:`line_observation_error` in closed form.

    Exists for speed only (see "Closed-form callbacks" in the module docstring); it
    must stay equal to ``line_observation_error`` followed by :func:`to_body`.

    With ``n = (cos α, sin α)`` and ``p = X ⊕ z_xy`` (the observed midpoint in the
    world), the landmark frame's y axis is ``−n``, so the offset of ``p`` from the
    line is ``e = ρ − p·n``, signed like ``z``'s normal: ``σ e`` with
    ``σ = sign cos(θ + z_θ − α − π/2)``; the angle is ``θ + z_θ − α − π/2`` modulo π.
    Jacobians, with ``φ = α − θ`` and ``t = p · (−sin α, cos α)``:

    * body tangent of ``X``: ``[[−σ cos φ, −σ sin φ, σ (z_y cos φ − z_x sin φ)], [0, 0, 1]]``;
    * ``(ρ, α)``: ``[[σ, −σ t], [0, −1]]``.
    """
    zx, zy, zt = float(z[0]), float(z[1]), float(z[2])
    czt, szt = math.cos(zt), math.sin(zt)
    angle_offset = zt - math.pi / 2.0
    # GTSAM copies H[i] on assignment, so one pair of Jacobian buffers per factor can
    # be refilled on every call (cheaper than building two new arrays).  The constant
    # entries are written once here.
    Jx = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    Jl = np.array([[0.0, 0.0], [0.0, -1.0]])

    def cb(
        this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None
    ) -> FloatArray:
        keys = this.keys()
        p = values.atPose2(keys[0])
        x, y, th = p.x(), p.y(), p.theta()
        # Python floats: scalar arithmetic on numpy scalars is several times slower.
        rho, alpha = values.atVector(keys[1]).tolist()
        c, s = math.cos(th), math.sin(th)
        ca, sa = math.cos(alpha), math.sin(alpha)
        px = x + c * zx - s * zy
        py = y + s * zx + c * zy
        cphi = ca * c + sa * s
        sphi = sa * c - ca * s
        # σ: sign of cos(θ + z_θ − α − π/2) = sin(θ + z_θ − α).
        sign = 1.0 if szt * cphi - czt * sphi >= 0.0 else -1.0
        r = np.array(
            [sign * (rho - px * ca - py * sa), wrap_scalar_half(th - alpha + angle_offset)]
        )
        if H is None:
            return r
        Jx[0, 0] = -sign * cphi
        Jx[0, 1] = -sign * sphi
        Jx[0, 2] = sign * (zy * cphi - zx * sphi)
        Jl[0, 0] = sign
        Jl[0, 1] = sign * (px * sa - py * ca)
        if _Checks.enabled:
            _check("line factor", r, (Jx, Jl), (3, 2))
        H[0] = Jx
        H[1] = Jl
        return r

    return cb


def _circle_cb(z: FloatArray, with_radius: bool = True) -> Callable[..., FloatArray]:
    """Callback of :func:`circle_factor`: :func:`circle_observation_error` in closed form;
    with ``with_radius=False`` that of :func:`circle_centre_factor` (its first two rows,
    on a 2-parameter centre).

    Exists for speed only, like :func:`_line_cb`.  The centre seen from ``X`` is
    ``l = R(θ)ᵀ (c − X_xy)``; the residual ``(z_xy − l, z_r − r)`` has the pose
    Jacobian ``[[c, s, −l_y], [−s, c, l_x], 0]`` in raw parameters, which
    :func:`to_body` turns into ``[[1, 0, −l_y], [0, 1, l_x], 0]``, and the circle
    Jacobian ``−blockdiag(R(θ)ᵀ, 1)``.
    """
    zx, zy, zr = float(z[0]), float(z[1]), float(z[2])
    n = 3 if with_radius else 2
    name = "circle factor" if with_radius else "circle centre factor"
    # Refilled on every call, as in _line_cb.
    Jx = np.zeros((n, 3))
    Jx[0, 0] = Jx[1, 1] = 1.0
    Jc = np.zeros((n, n))
    if with_radius:
        Jc[2, 2] = -1.0

    def cb(
        this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None
    ) -> FloatArray:
        keys = this.keys()
        p = values.atPose2(keys[0])
        x, y, th = p.x(), p.y(), p.theta()
        v = values.atVector(keys[1])
        c, s = math.cos(th), math.sin(th)
        dx, dy = float(v[0]) - x, float(v[1]) - y
        lx = c * dx + s * dy
        ly = -s * dx + c * dy
        if with_radius:
            r = np.array([zx - lx, zy - ly, zr - float(v[2])])
        else:
            r = np.array([zx - lx, zy - ly])
        if H is None:
            return r
        Jx[0, 2] = -ly
        Jx[1, 2] = lx
        Jc[0, 0] = -c
        Jc[0, 1] = -s
        Jc[1, 0] = s
        Jc[1, 1] = -c
        if _Checks.enabled:
            _check(name, r, (Jx, Jc), (3, n))
        H[0] = Jx
        H[1] = Jc
        return r

    return cb


def _as_measurement(z: FloatArray, name: str) -> FloatArray:
    arr = np.array(z, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{name}: measurement must be a finite (3,) array, got {z!r}")
    return arr


def line_factor(
    pose_key: int, line_key: int, z: FloatArray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """Line observation factor on (Pose2 ``pose_key``, line ``(ρ, α)`` ``line_key``).

    ``z`` is the SPmap line in the sensor frame; ``noise`` a 2-dim model, normally
    ``observation_noise(LINE, z, cov)``.  Residual: :func:`line_observation_error`.
    """
    zz = _as_measurement(z, "line factor")
    if noise.dim() != 2:
        raise ValueError(f"line factor needs a 2-dim noise model, got {noise.dim()}")
    return gtsam.CustomFactor(noise, [pose_key, line_key], _line_cb(zz))


def circle_factor(
    pose_key: int, circle_key: int, z: FloatArray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """Circle observation factor on (Pose2 ``pose_key``, circle ``(x, y, r)`` ``circle_key``)."""
    zz = _as_measurement(z, "circle factor")
    if zz[2] <= 0.0:
        raise ValueError(f"circle factor: radius must be > 0, got {zz[2]}")
    if noise.dim() != 3:
        raise ValueError(f"circle factor needs a 3-dim noise model, got {noise.dim()}")
    return gtsam.CustomFactor(noise, [pose_key, circle_key], _circle_cb(zz))


def circle_centre_factor(
    pose_key: int, centre_key: int, z: FloatArray, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """Centre part of a circle observation, on (Pose2 ``pose_key``, centre ``(x, y)``
    ``centre_key``): the first two rows of :func:`circle_observation_error` (the circle's
    radius is then a separate variable, see ``GraphOptions.split_circles``).  ``z`` is the
    whole observed circle; ``noise`` a 2-dim model of the centre block of its covariance.
    """
    zz = _as_measurement(z, "circle centre factor")
    if noise.dim() != 2:
        raise ValueError(f"circle centre factor needs a 2-dim noise model, got {noise.dim()}")
    return gtsam.CustomFactor(noise, [pose_key, centre_key], _circle_cb(zz, with_radius=False))


def observation_factor(
    kind: FeatureKind,
    pose_key: int,
    landmark_key: int,
    z: FloatArray,
    cov: FloatArray,
    robust: str | None = None,
    check: bool = True,
) -> gtsam.CustomFactor:
    """Line or circle observation factor with its propagated noise model, by kind."""
    if kind == FeatureKind.LINE:
        noise = observation_noise(kind, z, cov, robust, check)
        return line_factor(pose_key, landmark_key, z, noise)
    if kind == FeatureKind.CIRCLE:
        noise = observation_noise(kind, z, cov, robust, check)
        return circle_factor(pose_key, landmark_key, z, noise)
    raise ValueError(f"unknown feature kind {kind!r} (0 = line, 1 = circle)")


def _tie_factor(
    name: str,
    error: Callable[..., tuple[FloatArray, FloatArray, FloatArray, FloatArray]],
    keys: list[int],
    noise: gtsam.noiseModel.Base,
    dims: tuple[int, int, int],
) -> gtsam.CustomFactor:
    """A tie factor over (Pose2 anchor, landmark vector, known vector) keys.

    ``error(A, landmark, known)`` returns the residual and its Jacobians w.r.t. the raw
    anchor parameters, the landmark and the known feature; the anchor's is converted to
    GTSAM's body-frame tangent here, once for both feature kinds.
    """

    def cb(
        this: gtsam.CustomFactor, values: gtsam.Values, H: list[FloatArray] | None
    ) -> FloatArray:
        k = this.keys()
        a = values.atPose2(k[0])
        A = np.array([a.x(), a.y(), a.theta()])
        r, JA, JL, JK = error(A, values.atVector(k[1]), values.atVector(k[2]))
        if H is not None:
            JAb = to_body(JA, A[2])
            if _Checks.enabled:
                _check(name, r, (JAb, JL, JK), dims)
            H[0] = JAb
            H[1] = JL
            H[2] = JK
        return r

    return gtsam.CustomFactor(noise, keys, cb)


def line_tie_factor(
    anchor_key: int,
    landmark_key: int,
    known_key: int,
    t_known: float,
    noise: gtsam.noiseModel.Base,
) -> gtsam.CustomFactor:
    """Tie of a line landmark (``Wglobal``) to a known line (``Wknown``) through the anchor.

    Keys: Pose2 ``A = x^Wglobal_Wknown``, landmark ``(ρ, α)``, known ``(ρ, α)``.
    Residual :func:`line_tie_error` (2-dim).
    """
    if not math.isfinite(t_known):
        raise ValueError(f"line tie factor: t_known must be finite, got {t_known}")
    if noise.dim() != 2:
        raise ValueError(f"line tie factor needs a 2-dim noise model, got {noise.dim()}")
    t_k = float(t_known)

    def error(
        A: FloatArray, lm: FloatArray, kn: FloatArray
    ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
        return line_tie_error(A, lm, kn, t_k)

    return _tie_factor(
        "line tie factor", error, [anchor_key, landmark_key, known_key], noise, (3, 2, 2)
    )


def circle_tie_factor(
    anchor_key: int, landmark_key: int, known_key: int, noise: gtsam.noiseModel.Base
) -> gtsam.CustomFactor:
    """Tie of a circle landmark (``Wglobal``) to a known circle (``Wknown``): 3-dim residual."""
    if noise.dim() != 3:
        raise ValueError(f"circle tie factor needs a 3-dim noise model, got {noise.dim()}")
    return _tie_factor(
        "circle tie factor",
        circle_tie_error,
        [anchor_key, landmark_key, known_key],
        noise,
        (3, 3, 3),
    )
