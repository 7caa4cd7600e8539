"""Circle measurement model: an observed circle against a target circle (docs/method.md).

A circle is ``(x, y, r)``: centre and radius.  The residual of an observed circle
``Z`` against a target ``T`` (estimated or known, the same function) is
``Z − T = (x_Z − x_T, y_Z − y_T, r_Z − r_T)``; its noise is ``Σ_Z``.  The observation
form takes the target from the world through the sensor pose:
``r = circle_residual(⊖X ⊕ C, z)`` (:func:`circle_observation`), where a change of
frame moves the centre like a point and leaves the radius alone.

Every function is pure and returns its value with its Jacobians w.r.t. the raw
parameters.
"""

from __future__ import annotations

import numpy as np

from mapfuse_core.geometry.se2 import FloatArray, relative

__all__ = [
    "circle_observation",
    "circle_observation_cov",
    "circle_residual",
    "circle_residual_cov",
]


def circle_residual(T: FloatArray, Z: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual ``Z − T`` with ``∂r/∂T = −I`` and ``∂r/∂Z = I`` (3×3 each)."""
    eye = np.eye(3)
    return np.asarray(Z - T, dtype=np.float64), -eye, eye.copy()


def circle_residual_cov(T: FloatArray, Z: FloatArray, cov_Z: FloatArray) -> FloatArray:
    """Noise of :func:`circle_residual` due to the observation: ``Σ_Z`` (``∂r/∂Z = I``)."""
    del T, Z
    out: FloatArray = 0.5 * (cov_Z + cov_Z.T)
    return out


def circle_observation(
    X: FloatArray, C: FloatArray, z: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of circle ``z`` (sensor frame) against world circle ``C`` seen from pose ``X``.

    ``r = circle_residual(⊖X ⊕ C, z) = z − (R(θ)ᵀ (C_xy − X_xy), C_r)``.  Returns ``r``
    and ``∂r/∂X``, ``∂r/∂C`` (3×3 each).
    """
    centre = np.array([C[0], C[1], 0.0])
    v, JX, JC = relative(X, centre)
    T = np.array([v[0], v[1], C[2]])
    r, JrT, _ = circle_residual(T, z)
    JTX = np.zeros((3, 3))
    JTX[:2, :] = JX[:2, :]
    JTC = np.zeros((3, 3))
    JTC[:2, :2] = JC[:2, :2]
    JTC[2, 2] = 1.0
    return r, JrT @ JTX, JrT @ JTC


def circle_observation_cov(
    X: FloatArray, C: FloatArray, z: FloatArray, cov_z: FloatArray
) -> FloatArray:
    """Noise of :func:`circle_observation`: ``Σ_z``."""
    del X, C
    return circle_residual_cov(z, z, cov_z)
