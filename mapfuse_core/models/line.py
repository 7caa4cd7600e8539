"""Line measurement model: an observed segment against a line (docs/method.md).

A line is an SPmap frame ``(x, y, θ)`` on it with its x axis along it; an observed
segment is the SPmap frame of its fitted line placed at the segment's midpoint.  The
one residual of the model is the pairing of a segment ``Z`` with a target line ``T``
(estimated or known, the same function)::

    r = pairing(T, Z) = (lateral offset of Z's reference point from line T,
                         θ_Z − θ_T modulo π, in (−π/2, π/2])

i.e. ``B · (⊖T ⊕ Z)`` with the angle taken modulo π and the offset measured along
``T``'s normal oriented like ``Z``'s.  It does not depend on where ``T``'s reference
point sits along ``T``, nor on ``T``'s direction.  Its noise
is the segment's covariance with the along-line pseudo-variance projected out
(:func:`bind_line_cov`), propagated through ``∂r/∂Z``.

Where the lateral offset is measured is the model's one parameter (``at``):
``"observed"`` (above, the default) or ``"target"``, the offset of ``T``'s reference
point from line ``Z``, ``−B · (⊖Z ⊕ T)``: the paper's ties of two map lines (its eqs.
5 and 20, ``B · x^F_G``, ``G`` the target) measure there.  Where the two lines are
parallel the two values are equal; they differ by (angle between the lines ×
along-line distance between the two reference points).

The observation form takes the target from the world through the sensor pose:
``r = line_residual(⊖X ⊕ L, z)`` (:func:`line_observation`).

Every function is pure and returns its value with its Jacobians w.r.t. the raw
parameters (absolute perturbations of ``(x, y, θ)``).
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, relative, wrap_scalar_half

__all__ = [
    "B_LINE",
    "bind_line_cov",
    "line_observation",
    "line_observation_cov",
    "line_residual",
    "line_residual_cov",
]

#: Binding matrix of an SPmap line: keeps the lateral offset and the angle.
B_LINE: FloatArray = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])


def line_residual(
    T: FloatArray, Z: FloatArray, at: Literal["observed", "target"] = "observed"
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of segment ``Z`` against line ``T`` with ``∂r/∂T`` and ``∂r/∂Z`` (2×3 each).

    ``r[1]`` is the angle ``θ_Z − θ_T`` modulo π.  ``r[0]`` is a signed offset
    (metres), measured ``at``:

    * ``"observed"``: of ``Z``'s reference point from the line ``T``, along ``T``'s
      normal oriented like ``Z``'s (``T``'s y axis, turned by π when the two frames
      point more than π/2 apart).  Neither value depends on ``T``'s direction, so a
      target line's direction convention never changes the residual, nor the sign of
      its lateral/angle correlation (the noise, :func:`line_residual_cov`, is the
      segment's, in the segment's frame).  Zero when ``Z``'s reference point lies on
      ``T`` and the two are parallel; discontinuous only where they are perpendicular.
    * ``"target"``: of the line ``Z`` from ``T``'s reference point, along ``Z``'s normal
      (``−B · (⊖Z ⊕ T)`` when the two point less than π/2 apart): it depends on where
      ``T``'s reference point sits along ``T`` and not on ``Z``'s.  Zero when ``T``'s
      reference point lies on ``Z`` and the two are parallel.

    Where the lines are parallel (or anti-parallel) the two offsets are equal.
    """
    if at == "target":
        return _offset_at_target(T, Z)
    if at != "observed":
        raise ValueError(f"at must be 'observed' or 'target', got {at!r}")
    # relative() written out: this is the inner loop of every association.
    c, s = math.cos(T[2]), math.sin(T[2])
    dx, dy = float(Z[0] - T[0]), float(Z[1] - T[1])
    lx = c * dx + s * dy
    dth = float(Z[2] - T[2])
    # B·(⊖T ⊕ Z) with the lateral row oriented like Z's normal (rows of relative()'s
    # Jacobians kept by B_LINE, times the orientation).
    g = 1.0 if math.cos(dth) >= 0.0 else -1.0
    r = np.array([g * (-s * dx + c * dy), wrap_scalar_half(dth)])
    JrT = np.array([[g * s, -g * c, -g * lx], [0.0, 0.0, -1.0]])
    JrZ = np.array([[-g * s, g * c, 0.0], [0.0, 0.0, 1.0]])
    return r, JrT, JrZ


def _offset_at_target(T: FloatArray, Z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`line_residual` ``at="target"``: ``r[0] = n_Z · (p_Z − p_T)``, ``n_Z`` the
    normal (y axis) of ``Z``, ``p`` the reference points."""
    cz, sz = math.cos(Z[2]), math.sin(Z[2])
    dx, dy = float(Z[0] - T[0]), float(Z[1] - T[1])
    # ∂n_Z/∂θ_Z · (p_Z − p_T) = −u_Z · (p_Z − p_T): T's reference point along Z.
    along = -(cz * dx + sz * dy)
    r = np.array([-sz * dx + cz * dy, wrap_scalar_half(float(Z[2] - T[2]))])
    JrT = np.array([[sz, -cz, 0.0], [0.0, 0.0, -1.0]])
    JrZ = np.array([[-sz, cz, along], [0.0, 0.0, 1.0]])
    return r, JrT, JrZ


def bind_line_cov(line: FloatArray, cov: FloatArray) -> FloatArray:
    """Covariance of an SPmap line with its along-line component projected out.

    ``Π Σ Πᵀ`` with ``Π = blockdiag(I − u uᵀ, 1)``, ``u`` the line's direction: the
    reference point's position along its own line is a gauge (a pseudo-variance such
    as extraction's ``L²/12``), not a noise of the line.
    """
    c, s = math.cos(line[2]), math.sin(line[2])
    P = np.array([[1 - c * c, -c * s, 0.0], [-c * s, 1 - s * s, 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = P @ cov @ P.T
    return out


def line_residual_cov(T: FloatArray, Z: FloatArray, cov_Z: FloatArray) -> FloatArray:
    """Noise of :func:`line_residual` due to the segment: ``J_Z bind(Z, Σ_Z) J_Zᵀ`` (2×2).

    At ``T = Z`` (the zero-residual point) this is the (lateral, angle) block of
    ``Σ_Z`` in the segment's own frame.  Evaluated as ``(J_Z Π) Σ_Z (J_Z Π)ᵀ`` with
    ``Π`` the projection of :func:`bind_line_cov` (it runs for every candidate
    pairing of the EKF).
    """
    c, s = math.cos(T[2]), math.sin(T[2])
    cz, sz = math.cos(Z[2]), math.sin(Z[2])
    # J_Z's lateral row is ±T's normal n = (−s, c) (oriented like Z's); Π removes its
    # component along u_Z.
    sign = 1.0 if c * cz + s * sz >= 0.0 else -1.0
    d = c * sz - s * cz
    M = np.array([[sign * (-s - d * cz), sign * (c - d * sz), 0.0], [0.0, 0.0, 1.0]])
    out: FloatArray = M @ cov_Z @ M.T
    return 0.5 * (out + out.T)


def line_observation(
    X: FloatArray, L: FloatArray, z: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of segment ``z`` (sensor frame) against world line ``L`` seen from pose ``X``.

    ``r = line_residual(⊖X ⊕ L, z)``: the offset of the observed midpoint ``X ⊕ z_xy``
    from ``L`` and the angle between them.  Returns ``r`` and ``∂r/∂X``, ``∂r/∂L``
    (2×3 each).
    """
    T, JX, JL = relative(X, L)
    r, JrT, _ = line_residual(T, z)
    return r, JrT @ JX, JrT @ JL


def line_observation_cov(
    X: FloatArray, L: FloatArray, z: FloatArray, cov_z: FloatArray
) -> FloatArray:
    """Noise of :func:`line_observation`: :func:`line_residual_cov` at ``T = ⊖X ⊕ L``."""
    T, _, _ = relative(X, L)
    return line_residual_cov(T, z, cov_z)
