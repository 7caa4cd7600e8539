"""The measurement models by feature kind: one entry point per use, dispatching to
:mod:`mapfuse_core.models.line` or :mod:`mapfuse_core.models.circle`.

The EKF evaluates its pairings through :func:`pairing_residual` and
:func:`pairing_cov`; the factor graph calls the models directly (its hot-path
callbacks are closed forms of them, held equal by tests).
"""

from __future__ import annotations

from typing import Literal

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.models.circle import circle_observation, circle_residual, circle_residual_cov
from mapfuse_core.models.line import line_observation, line_residual, line_residual_cov

__all__ = ["circle_pairing", "line_pairing", "observe", "pairing_cov", "pairing_residual"]

#: SPmap pairing of two lines: :func:`mapfuse_core.models.line.line_residual`.
line_pairing = line_residual

#: Pairing of two circles: :func:`mapfuse_core.models.circle.circle_residual`.
circle_pairing = circle_residual


def pairing_residual(
    kind: FeatureKind,
    target: FloatArray,
    observed: FloatArray,
    at: Literal["observed", "target"] = "observed",
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Residual of ``observed`` against ``target`` (both of ``kind``, in one frame).

    Dispatches to :func:`~mapfuse_core.models.line.line_residual` (``at``: where a
    line's lateral offset is measured) or
    :func:`~mapfuse_core.models.circle.circle_residual` (a difference of centres and
    radii: ``at`` does not apply); returns the residual and its Jacobians w.r.t.
    ``target`` and ``observed``.
    """
    if kind == FeatureKind.LINE:
        return line_residual(target, observed, at)
    return circle_residual(target, observed)


def pairing_cov(
    kind: FeatureKind, target: FloatArray, observed: FloatArray, cov: FloatArray
) -> FloatArray:
    """Noise of :func:`pairing_residual` due to ``observed`` (covariance ``cov``), by kind."""
    if kind == FeatureKind.LINE:
        return line_residual_cov(target, observed, cov)
    return circle_residual_cov(target, observed, cov)


def observe(
    kind: FeatureKind, z: FloatArray, x_W_R: FloatArray, f_W: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Observation residual of measurement ``z`` (in the sensor frame ``R``), by kind.

    ``residual = pairing(⊖x_W_R ⊕ f_W, z)``: zero when the feature ``f_W`` (in ``W``)
    seen from pose ``x_W_R`` coincides with the measurement.  Dispatches to
    :func:`~mapfuse_core.models.line.line_observation` or
    :func:`~mapfuse_core.models.circle.circle_observation`; returns the residual (2 for
    a line, 3 for a circle) and its Jacobians w.r.t. ``x_W_R`` and ``f_W``.
    """
    if kind == FeatureKind.LINE:
        return line_observation(x_W_R, f_W, z)
    return circle_observation(x_W_R, f_W, z)
