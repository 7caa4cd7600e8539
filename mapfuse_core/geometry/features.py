"""Map features: representations, frame changes and dispatch by kind (docs/method.md §2).

Two feature kinds, each a length-3 float array:

* **Line** (SPmap, Castellanos): a frame ``(x, y, θ)`` lying on the line with its x
  axis along the line.  Only the lateral offset and the angle are real degrees of
  freedom.  An observed segment's reference point is its midpoint, and the residual
  is that point's offset from the target line, so where a target line's own
  reference point sits along it never enters a residual.  Angles of lines are
  compared modulo π.
  Covariances are of the absolute ``(x, y, θ)`` parameters in the frame the line is
  expressed in; the along-line variance is a pseudo-variance (see extraction).
* **Circle** ``(x, y, r)``: centre and radius; a change of frame moves the centre
  like a point and leaves ``r`` alone.

Every function returns its value together with its Jacobians.  The measurement
models live above this module, in :mod:`mapfuse_core.models` (one per feature type,
and :mod:`mapfuse_core.models.dispatch` to pick one by kind).
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np

from mapfuse_core.geometry.se2 import (
    FloatArray,
    compose_jacobians,
    relative,
    transform_point_jacobians,
    wrap_scalar,
)

__all__ = [
    "FeatureKind",
    "canonical_line",
    "express_circle_in",
    "express_in",
    "express_line_in",
    "line_from_normal",
    "line_to_normal",
    "normal_to_line",
    "residual_dim",
    "transform_circle",
    "transform_feature",
    "transform_line",
]


class FeatureKind(IntEnum):
    """Feature type code, stored as an integer in measurement logs."""

    LINE = 0
    CIRCLE = 1


def residual_dim(kind: FeatureKind) -> int:
    """Dimension of the pairing residual: 2 for a line, 3 for a circle."""
    return 2 if kind == FeatureKind.LINE else 3


# --------------------------------------------------------------------------- lines


def line_to_normal(line: FloatArray) -> tuple[FloatArray, FloatArray]:
    """SPmap line → normal form ``(ρ, α)`` with ``ρ ≥ 0``, and ``∂(ρ, α)/∂(x, y, θ)`` (2×3).

    Points ``p`` of the line satisfy ``p · (cos α, sin α) = ρ``.  Undefined (raises) for
    a line through the origin only in the sense that α is then the θ+π/2 branch.
    """
    x, y, th = float(line[0]), float(line[1]), float(line[2])
    s, c = math.sin(th), math.cos(th)
    rho_signed = -x * s + y * c
    sign = 1.0 if rho_signed >= 0.0 else -1.0
    rho = sign * rho_signed
    alpha = wrap_scalar(th + sign * math.pi / 2.0)
    J = np.array([[-sign * s, sign * c, sign * (-x * c - y * s)], [0.0, 0.0, 1.0]])
    return np.array([rho, alpha]), J


def normal_to_line(rho: float, alpha: float) -> FloatArray:
    """Normal form → SPmap line at the foot of the normal, y axis towards the origin."""
    return line_from_normal(rho, alpha, 0.0)[0]


def line_from_normal(rho: float, alpha: float, t: float) -> tuple[FloatArray, FloatArray]:
    """SPmap line from ``(ρ, α)`` with its origin ``t`` metres along the line from the foot.

    The frame's x axis points along ``α + π/2`` so that its y axis points from the line
    towards the origin of the frame the line is given in (the sensor, for an
    observation).  Returns the line and ``∂(x, y, θ)/∂(ρ, α, t)`` (3×3).
    """
    ca, sa = math.cos(alpha), math.sin(alpha)
    line = np.array([rho * ca - t * sa, rho * sa + t * ca, wrap_scalar(alpha + math.pi / 2)])
    J = np.array(
        [
            [ca, -rho * sa - t * ca, -sa],
            [sa, rho * ca - t * sa, ca],
            [0.0, 1.0, 0.0],
        ]
    )
    return line, J


def canonical_line(line: FloatArray) -> FloatArray:
    """Same line with θ flipped by π if needed so that its y axis points to the origin.

    The along-line coordinate is unchanged; only the direction convention is fixed,
    which matters for plotting and association, not for residuals (angles modulo π).
    """
    x, y, th = float(line[0]), float(line[1]), float(line[2])
    lateral_of_origin = math.sin(th) * x - math.cos(th) * y
    if lateral_of_origin < 0.0:
        th = wrap_scalar(th + math.pi)
    return np.array([x, y, th])


def transform_line(T: FloatArray, line: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Line given in frame ``T`` → the frame ``T`` is given in: ``T ⊕ L`` with Jacobians."""
    return compose_jacobians(T, line)


def express_line_in(T: FloatArray, line: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Line given in the parent of ``T`` → frame ``T``: ``⊖T ⊕ L`` with Jacobians."""
    return relative(T, line)


# --------------------------------------------------------------------------- circles


def transform_circle(
    T: FloatArray, circle: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Circle given in frame ``T`` → the frame ``T`` is given in, with Jacobians (3×3)."""
    p, Jt2, Jp = transform_point_jacobians(T, circle[:2])
    value = np.array([p[0], p[1], circle[2]])
    JT = np.zeros((3, 3))
    JT[:2, :] = Jt2
    JC = np.zeros((3, 3))
    JC[:2, :2] = Jp
    JC[2, 2] = 1.0
    return value, JT, JC


def express_circle_in(
    T: FloatArray, circle: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Circle given in the parent of ``T`` → frame ``T``, with Jacobians (3×3)."""
    c, s = math.cos(T[2]), math.sin(T[2])
    dx, dy = circle[0] - T[0], circle[1] - T[1]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    value = np.array([lx, ly, circle[2]])
    JT = np.array([[-c, -s, ly], [s, -c, -lx], [0.0, 0.0, 0.0]])
    JC = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return value, JT, JC


# --------------------------------------------------------------------------- dispatch


def transform_feature(
    kind: FeatureKind, T: FloatArray, f: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Feature given in frame ``T`` → parent frame (``T ⊕ f``), by kind."""
    return transform_line(T, f) if kind == FeatureKind.LINE else transform_circle(T, f)


def express_in(
    kind: FeatureKind, T: FloatArray, f: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Feature given in the parent of ``T`` → frame ``T`` (``⊖T ⊕ f``), by kind."""
    return express_line_in(T, f) if kind == FeatureKind.LINE else express_circle_in(T, f)
