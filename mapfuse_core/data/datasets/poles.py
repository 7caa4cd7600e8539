"""Beacon poles in a car-park scan: clusters of reflective returns as circles."""

from __future__ import annotations

import itertools
import math
from typing import TYPE_CHECKING

import numpy as np

from mapfuse_core.data.datasets.common import BEAM_SPACING_RAD
from mapfuse_core.geometry.se2 import FloatArray

if TYPE_CHECKING:
    from mapfuse_core.data.datasets.carpark_options import CarparkOptions

_NO_RETURN_M = 81.91
"""Range the car-park SICK reports for "no return"."""


def _circle_cov(
    rho: float, beta: float, var_radial: float, var_tangential: float, var_r: float
) -> FloatArray:
    """Covariance of ``(x, y, r)`` for a centre with the given radial/tangential variances."""
    c, s = math.cos(beta), math.sin(beta)
    R = np.array([[c, -s], [s, c]])
    cov = np.zeros((3, 3))
    cov[:2, :2] = R @ np.diag([var_radial, var_tangential]) @ R.T
    cov[2, 2] = var_r
    return cov


def detect_reflector_poles(
    ranges: FloatArray, intensity: FloatArray, options: CarparkOptions
) -> tuple[list[tuple[FloatArray, FloatArray, int]], dict[str, int]]:
    """Beacon poles in one car-park scan: ``[(circle (x, y, r), cov 3×3, n_points)]``.

    Returns the poles in the laser frame and rejection counts.  Reflective returns
    (non-zero ``intensity``) within ``max_range_m`` are grouped by beam index and
    distance; the pole's centre lies ``pole_radius_m`` behind the mean range along the
    mean bearing.  A pole of 6 cm gives 1 to 6 returns, too few to fit a radius, so the
    radius is the known one (variance ``pole_radius_sigma_m²``, uncorrelated with the
    centre) and only the centre is estimated.  The centre's radial variance is
    ``σρ² + σ_r²`` (the surface-to-centre offset is uncertain by the radius error);
    its tangential variance ``ρ²(σβ² + Δβ²/24)`` adds the quantisation of the two
    cluster edges (each uniform over one beam) to the bearing noise.
    """
    rng_ = np.asarray(ranges, dtype=np.float64)
    bearings = np.arange(rng_.shape[0]) * BEAM_SPACING_RAD - math.pi / 2.0
    bearings = bearings + options.bearing_offset_rad
    reflective = (np.asarray(intensity) > 0) & (rng_ < _NO_RETURN_M - 0.5)
    rejected: dict[str, int] = {}
    far = reflective & (rng_ > options.max_range_m)
    if np.any(far):
        rejected["beyond_max_range"] = int(far.sum())
    idx = np.nonzero(reflective & ~far)[0]
    if idx.size == 0:
        return [], rejected
    pts = rng_[idx, None] * np.column_stack((np.cos(bearings[idx]), np.sin(bearings[idx])))
    split = (np.diff(idx) > options.cluster_max_beam_gap) | (
        np.hypot(*np.diff(pts, axis=0).T) > options.cluster_max_gap_m
    )
    bounds = np.concatenate(([0], np.nonzero(split)[0] + 1, [idx.size]))
    r0 = options.pole_radius_m
    var_r = options.pole_radius_sigma_m**2
    var_beta = options.sigma_bearing_rad**2 + BEAM_SPACING_RAD**2 / 24.0
    poles: list[tuple[FloatArray, FloatArray, int]] = []
    for lo, hi in itertools.pairwise(bounds):
        if float(np.hypot(*(pts[hi - 1] - pts[lo]))) > options.max_cluster_width_m:
            rejected["cluster_too_wide"] = rejected.get("cluster_too_wide", 0) + 1
            continue
        beta = float(np.mean(bearings[idx[lo:hi]]))
        rho = float(np.mean(rng_[idx[lo:hi]])) + r0
        circle = np.array([rho * math.cos(beta), rho * math.sin(beta), r0])
        cov = _circle_cov(rho, beta, options.sigma_range_m**2 + var_r, rho * rho * var_beta, var_r)
        poles.append((circle, cov, int(hi - lo)))
    return poles, rejected
