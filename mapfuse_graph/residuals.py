"""Residual functions of the graph's factors and the landmark helpers they share.

Pure functions of arrays returning the residual and its Jacobians with respect to the
raw parameters (``(x, y, θ)`` for poses, ``(ρ, α)`` for lines, ``(x, y, r)`` for
circles), plus the conversions between the SPmap line form and the graph's signed
normal form.  :mod:`mapfuse_graph.factors` describes the variables and builds the GTSAM
factors from these functions.
"""

from __future__ import annotations

import math

import gtsam
import numpy as np

from mapfuse_core.geometry.features import (
    FeatureKind,
    line_from_normal,
    transform_circle,
    transform_feature,
    transform_line,
)
from mapfuse_core.geometry.se2 import FloatArray, wrap_scalar
from mapfuse_core.models import pairing_residual
from mapfuse_core.models.circle import circle_observation
from mapfuse_core.models.line import line_observation, line_residual, line_residual_cov

__all__ = [
    "circle_observation_error",
    "circle_tie_error",
    "known_line_prior_cov",
    "known_line_prior_error",
    "landmark_from_observation",
    "line_observation_error",
    "line_observation_residual",
    "line_tie_error",
    "line_to_rho_alpha",
    "pose_of",
    "rho_alpha_along",
    "to_body",
    "to_spmap_feature",
]

# --------------------------------------------------------------------------- helpers


def to_body(J_abs: FloatArray, theta: float) -> FloatArray:
    """Jacobian w.r.t. raw ``(x, y, θ)`` → w.r.t. GTSAM's body-frame Pose2 tangent.

    ``∂/∂δ = J_abs · blockdiag(R(θ), 1)`` because ``X ⊕ Exp(δ)`` moves the position by
    ``R(θ) δ_xy`` and the heading by ``δ_θ`` to first order.
    """
    c, s = math.cos(theta), math.sin(theta)
    out: FloatArray = J_abs @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out


def pose_of(p: gtsam.Pose2) -> FloatArray:
    """A ``gtsam.Pose2`` as the ``(x, y, θ)`` array mapfuse uses."""
    return np.array([p.x(), p.y(), p.theta()])


def line_to_rho_alpha(line: FloatArray) -> tuple[FloatArray, FloatArray]:
    """SPmap line ``(x, y, θ)`` → signed normal form ``(ρ, α)`` and ``∂(ρ, α)/∂(x, y, θ)``.

    ``α = θ − π/2`` (wrapped) and ``ρ = x sin θ − y cos θ``, the exact inverse of
    ``line_from_normal(ρ, α, t)`` for the ``t`` of the SPmap origin
    (:func:`rho_alpha_along`).  Unlike :func:`mapfuse_core.geometry.features.line_to_normal`
    the sign of ``ρ`` is kept, so the map is smooth everywhere.
    """
    x, y, th = float(line[0]), float(line[1]), float(line[2])
    s, c = math.sin(th), math.cos(th)
    value = np.array([x * s - y * c, wrap_scalar(th - math.pi / 2.0)])
    J = np.array([[s, -c, x * c + y * s], [0.0, 0.0, 1.0]])
    return value, J


def rho_alpha_along(ra: FloatArray, point: FloatArray) -> float:
    """Along-line coordinate ``t`` of the foot of ``point`` on line ``(ρ, α)``."""
    return float(-point[0] * math.sin(ra[1]) + point[1] * math.cos(ra[1]))


def to_spmap_feature(
    kind: FeatureKind, v: FloatArray, cov: FloatArray, t: float = 0.0
) -> tuple[FloatArray, FloatArray]:
    """Graph variable → the feature array mapfuse uses, with its covariance.

    Lines ``(ρ, α)`` become the SPmap frame ``t`` metres along the line from the foot
    of the normal (covariance through ``∂(x, y, θ)/∂(ρ, α)``, zero along the line);
    circles are returned unchanged.
    """
    if kind == FeatureKind.CIRCLE:
        return np.asarray(v, dtype=float).copy(), np.asarray(cov, dtype=float).copy()
    line, J = line_from_normal(float(v[0]), float(v[1]), t)
    Jra = J[:, :2]
    return line, Jra @ cov @ Jra.T


def landmark_from_observation(kind: FeatureKind, x_W_R: FloatArray, z: FloatArray) -> FloatArray:
    """Initial landmark variable (in ``W``) from an observation ``z`` taken at ``x_W_R``."""
    f = transform_feature(kind, x_W_R, z)[0]
    if kind == FeatureKind.CIRCLE:
        return f
    return line_to_rho_alpha(f)[0]


# --------------------------------------------------------------------------- error functions
# Pure functions of arrays returning the residual and its Jacobians w.r.t. the raw
# parameters: (x, y, θ) for poses, (ρ, α) for lines, (x, y, r) for circles.


def line_observation_error(
    z: FloatArray, x_W_R: FloatArray, ra: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Line observation residual ``line_observation(X, L(ρ, α), z)`` and Jacobians (2×3, 2×2).

    The offset of the observed segment's midpoint ``X ⊕ z_xy`` from the landmark line
    and the angle between them.  The landmark's SPmap frame is taken at the foot of
    the normal (``t = 0``); the residual does not depend on where along the line it is.
    """
    f, JF = line_from_normal(float(ra[0]), float(ra[1]), 0.0)
    r, Jx, Jf = line_observation(x_W_R, f, z)
    return r, Jx, Jf @ JF[:, :2]


def line_observation_residual(z: FloatArray, x_W_R: FloatArray, ra: FloatArray) -> FloatArray:
    """:func:`line_observation_error` without the Jacobians (error-only calls)."""
    return line_observation_error(z, x_W_R, ra)[0]


def circle_observation_error(
    z: FloatArray, x_W_R: FloatArray, c: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Circle observation residual ``circle_observation(X, C, z)`` and Jacobians (3×3, 3×3)."""
    return circle_observation(x_W_R, c, z)


def line_tie_error(
    A: FloatArray, landmark: FloatArray, known: FloatArray, t_known: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Known-map tie for lines: ``pairing(L, A ⊕ K)`` and Jacobians w.r.t. A, L, K.

    ``A = x^Wglobal_Wknown``; ``L = (ρ, α)`` in ``Wglobal``; ``K = (ρ, α)`` in ``Wknown``
    whose SPmap origin is held ``t_known`` metres along the line (the known wall's
    reference point, fixed when the factor is made).  The lateral residual is the
    offset of that point from ``L``, independent of where ``L``'s own origin is.
    Returns ``(r, J_A (2×3), J_L (2×2), J_K (2×2))``.
    """
    fL, JL = line_from_normal(float(landmark[0]), float(landmark[1]), 0.0)
    fK, JK = line_from_normal(float(known[0]), float(known[1]), t_known)
    pred, JA, JpK = transform_line(A, fK)
    r, J1, J2 = pairing_residual(FeatureKind.LINE, fL, pred)
    return r, J2 @ JA, J1 @ JL[:, :2], J2 @ JpK @ JK[:, :2]


def circle_tie_error(
    A: FloatArray, landmark: FloatArray, known: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Known-map tie for circles: ``pairing(C, A ⊕ K)`` and Jacobians w.r.t. A, C, K (3×3)."""
    pred, JA, JK = transform_circle(A, known)
    r, J1, J2 = pairing_residual(FeatureKind.CIRCLE, landmark, pred)
    return r, J2 @ JA, J1, J2 @ JK


def known_line_prior_error(ra: FloatArray, known: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Prior of a known wall on its ``(ρ, α)`` variable: ``line_residual(L(ρ, α), known)``.

    ``known = (m_x, m_y, θ₀)`` is the surveyed wall (a point on it and its direction);
    the residual is the offset of the surveyed point from the line ``(ρ, α)`` and the
    angle between them, the line model the EKF pairs a known wall with.  A Gaussian
    directly on ``(ρ, α)`` would linearise ``ρ`` about the foot of the origin, which
    for a wall far from it bends the prior (docs/method.md).  Returns
    ``(r (2,), ∂r/∂(ρ, α) (2×2))``.
    """
    f, JF = line_from_normal(float(ra[0]), float(ra[1]), 0.0)
    r, JT, _ = line_residual(f, known)
    return r, JT @ JF[:, :2]


def known_line_prior_cov(known: FloatArray, cov: FloatArray) -> FloatArray:
    """Covariance of :func:`known_line_prior_error` from the wall's SPmap ``cov`` (3×3).

    The model's noise at the zero-residual point, ``line_residual_cov(known, known,
    cov)``: the (lateral, angle) block of ``cov`` in the wall's own frame.
    """
    return line_residual_cov(known, known, np.asarray(cov, dtype=float))
