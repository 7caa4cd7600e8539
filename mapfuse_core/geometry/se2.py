"""SE(2) geometry with analytic Jacobians (``docs/method.md`` §1).

Every pose, frame and tangent vector in mapfuse is a length-3 float array ordered
``(x, y, θ)``: position in metres, heading in radians wrapped to ``(−π, π]``.
``x_A_B`` is the location of frame ``B`` expressed in frame ``A``.

All functions are pure: they take arrays, return new arrays, and return the
Jacobians next to the value so that the EKF and the factor graph linearise with
the same code.  Jacobians are with respect to the raw ``(x, y, θ)`` parameters
(absolute perturbations), which is what the EKF uses; the graph converts to
GTSAM's body-frame tangent where needed.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

__all__ = [
    "FloatArray",
    "as_pose",
    "compose",
    "compose_jacobians",
    "inverse",
    "inverse_jacobian",
    "relative",
    "rot2",
    "transform_point",
    "transform_point_jacobians",
    "wrap_angle",
    "wrap_angle_half",
    "wrap_scalar",
    "wrap_scalar_half",
]


def wrap_angle(a: ArrayLike) -> FloatArray:
    """Wrap angle(s) to ``(−π, π]``.

    ``π`` maps to ``π`` and ``−π`` maps to ``π`` so that the result is unique.
    """
    arr = np.asarray(a, dtype=np.float64)
    w = np.mod(arr + math.pi, 2.0 * math.pi) - math.pi
    # np.mod lands exactly on −π for odd multiples of π; move it to the closed end.
    return np.where(w <= -math.pi, w + 2.0 * math.pi, w)


def wrap_angle_half(a: ArrayLike) -> FloatArray:
    """Wrap angle(s) to ``(−π/2, π/2]``: angles of undirected lines, modulo π."""
    arr = np.asarray(a, dtype=np.float64)
    w = np.mod(arr + math.pi / 2.0, math.pi) - math.pi / 2.0
    return np.where(w <= -math.pi / 2.0, w + math.pi, w)


def wrap_scalar(a: float) -> float:
    """:func:`wrap_angle` for one float, without numpy overhead (hot paths)."""
    w = math.fmod(a + math.pi, 2.0 * math.pi)
    if w <= 0.0:
        w += 2.0 * math.pi
    return w - math.pi


def wrap_scalar_half(a: float) -> float:
    """:func:`wrap_angle_half` for one float."""
    w = math.fmod(a + math.pi / 2.0, math.pi)
    if w <= 0.0:
        w += math.pi
    return w - math.pi / 2.0


def as_pose(p: ArrayLike, name: str = "pose") -> FloatArray:
    """Validate and copy a pose-like input into a finite float array of shape (3,)."""
    arr = np.array(p, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,) ordered (x, y, θ), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} has a non-finite entry: {arr.tolist()}")
    return arr


def rot2(theta: float) -> FloatArray:
    """2×2 rotation matrix of angle ``theta``."""
    c, s = math.cos(theta), math.sin(theta)
    return np.array([[c, -s], [s, c]])


def compose(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a ⊕ b``: pose ``b`` given in frame ``a``, expressed in the frame ``a`` is given in."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [
            a[0] + c * b[0] - s * b[1],
            a[1] + s * b[0] + c * b[1],
            wrap_scalar(float(a[2] + b[2])),
        ]
    )


def compose_jacobians(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``a ⊕ b`` with ``J1 = ∂(a⊕b)/∂a`` and ``J2 = ∂(a⊕b)/∂b`` (both 3×3)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    J1 = np.array(
        [
            [1.0, 0.0, -s * b[0] - c * b[1]],
            [0.0, 1.0, c * b[0] - s * b[1]],
            [0.0, 0.0, 1.0],
        ]
    )
    J2 = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return compose(a, b), J1, J2


def inverse(a: FloatArray) -> FloatArray:
    """``⊖a``: if ``a = x_A_B`` then ``⊖a = x_B_A``."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return np.array(
        [
            -c * a[0] - s * a[1],
            s * a[0] - c * a[1],
            wrap_scalar(-float(a[2])),
        ]
    )


def inverse_jacobian(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``⊖a`` with ``J = ∂(⊖a)/∂a`` (3×3)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    J = np.array(
        [
            [-c, -s, s * a[0] - c * a[1]],
            [s, -c, c * a[0] + s * a[1]],
            [0.0, 0.0, -1.0],
        ]
    )
    return inverse(a), J


def relative(a: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """``⊖a ⊕ b`` (``b`` seen from ``a``) with Jacobians w.r.t. ``a`` and ``b``.

    Written directly rather than through :func:`inverse` and :func:`compose` because it
    is the inner loop of every measurement model.
    """
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    lx = c * dx + s * dy
    ly = -s * dx + c * dy
    value = np.array([lx, ly, wrap_scalar(float(b[2] - a[2]))])
    Ja = np.array([[-c, -s, ly], [s, -c, -lx], [0.0, 0.0, -1.0]])
    Jb = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
    return value, Ja, Jb


def transform_point(a: FloatArray, p: FloatArray) -> FloatArray:
    """Point ``p`` given in frame ``a``, expressed in the frame ``a`` is given in.

    ``p`` may also be an ``(M, 2)`` array of points, all moved at once.
    """
    c, s = math.cos(a[2]), math.sin(a[2])
    q = np.asarray(p, dtype=float)
    x, y = q[..., 0], q[..., 1]
    return np.stack((a[0] + c * x - s * y, a[1] + s * x + c * y), axis=-1)


def transform_point_jacobians(
    a: FloatArray, p: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`transform_point` with ``∂/∂a`` (2×3) and ``∂/∂p`` (2×2)."""
    c, s = math.cos(a[2]), math.sin(a[2])
    Ja = np.array([[1.0, 0.0, -s * p[0] - c * p[1]], [0.0, 1.0, c * p[0] - s * p[1]]])
    Jp = np.array([[c, -s], [s, c]])
    return transform_point(a, p), Ja, Jp
