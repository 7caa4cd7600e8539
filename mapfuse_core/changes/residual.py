"""Residual coordinates of one feature relative to another: :func:`feature_residual`.

Lines: ``(b₀, φ)``, the lateral offset of the other line where it crosses the normal
through the reference point, and the angle between the lines (modulo π).  With
``v = ⊖L_ref ⊕ L = (a, b, φ)``, ``b₀ = b − a·tan φ``; moving ``L``'s origin along
its own line leaves ``b₀`` unchanged, so an observed segment's along-line
pseudo-variance does not enter.  Circles: ``(dx, dy, dr)``.
"""

from __future__ import annotations

import math

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, relative, wrap_scalar_half

__all__ = ["feature_residual", "residual_dof"]


def residual_dof(kind: FeatureKind) -> int:
    """Degrees of freedom of the residual: 2 for a line, 3 for a circle."""
    return 2 if kind == FeatureKind.LINE else 3


def feature_residual(
    kind: FeatureKind, reference: FloatArray, f: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of ``f`` from ``reference`` (one frame) and its Jacobians (ref, f)."""
    if kind == FeatureKind.CIRCLE:
        eye = np.eye(3)
        return np.asarray(f - reference, dtype=float), -eye, eye.copy()
    v, Ja, Jb = relative(reference, f)
    phi = wrap_scalar_half(float(v[2]))
    t = math.tan(phi)
    r = np.array([v[1] - v[0] * t, phi])
    Jv = np.array([[-t, 1.0, -v[0] / math.cos(phi) ** 2], [0.0, 0.0, 1.0]])
    return r, Jv @ Ja, Jv @ Jb
