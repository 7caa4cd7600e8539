"""Hostile detections: spurious features per scan and gross outliers on real ones.

:func:`~mapfuse_core.sim.simulate.simulate` applies :class:`ClutterParams` to the
extracted features of every scan, with its own random stream (the fourth child of the
run's :class:`numpy.random.SeedSequence`), so a run with clutter has the same
trajectory, scans and known map as the same seed without it.

* **Clutter**: ``features_per_scan`` spurious features are appended to every scan,
  circles with probability ``circle_fraction``, lines otherwise, at a uniform bearing
  in the field of view and a uniform range in ``[1 m, max_range_m]``.  A circle has a
  radius uniform in ``[0.1, 0.8]`` m and covariance ``diag(0.05², 0.05², 0.03²)``; a
  line has a uniform direction (its SPmap ``y`` axis towards the sensor, as
  extraction states it), a length uniform in ``[2, 12]`` m, lateral σ 2 cm, angle
  σ 0.005 rad and the along-line pseudo-variance ``L²/12`` of extraction.  Their
  ``true_id`` is −1: they belong to no world feature.
* **Gross outliers**: each real feature is, with probability ``outlier_fraction``,
  displaced by a distance uniform in ``[outlier_min_m, outlier_max_m]``, a circle in
  a uniform direction, a line along its normal (a move along a line changes nothing
  a matcher sees).  The stated covariance, ``true_id``, points and extent are kept:
  an outlier claims its usual precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import rot2
from mapfuse_core.perception.extraction import ExtractedFeature, ExtractionResult
from mapfuse_core.sensor import LaserParams

__all__ = ["ClutterParams", "add_clutter"]

_CIRCLE_SIGMA_M = 0.05
_CIRCLE_SIGMA_R_M = 0.03
_LINE_SIGMA_LAT_M = 0.02
_LINE_SIGMA_THETA_RAD = 0.005


@dataclass(frozen=True)
class ClutterParams:
    """Spurious features and gross outliers added to the extracted features."""

    features_per_scan: int = 0
    """Spurious features appended to every scan (≥ 0)."""
    circle_fraction: float = 0.5
    """Probability that a spurious feature is a circle (else a line), in ``[0, 1]``."""
    max_range_m: float = 30.0
    """Largest range of a spurious feature (m, > 1; capped by the laser's range)."""
    outlier_fraction: float = 0.0
    """Probability that a real feature is grossly displaced, in ``[0, 1]``."""
    outlier_min_m: float = 2.0
    """Smallest displacement of an outlier (m, ≥ 0)."""
    outlier_max_m: float = 10.0
    """Largest displacement of an outlier (m, ≥ ``outlier_min_m``)."""

    def __post_init__(self) -> None:
        n = self.features_per_scan
        if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 0:
            raise ValueError(f"ClutterParams.features_per_scan must be an integer >= 0, got {n!r}")
        for name in ("circle_fraction", "outlier_fraction"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and 0.0 <= v <= 1.0):
                raise ValueError(f"ClutterParams.{name} must be in [0, 1], got {v!r}")
        for name in ("max_range_m", "outlier_min_m", "outlier_max_m"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v)):
                raise ValueError(f"ClutterParams.{name} must be a finite number, got {v!r}")
        if self.max_range_m <= 1.0:
            raise ValueError(f"ClutterParams.max_range_m must be > 1, got {self.max_range_m}")
        if not 0.0 <= self.outlier_min_m <= self.outlier_max_m:
            raise ValueError(
                "ClutterParams needs 0 <= outlier_min_m <= outlier_max_m, got "
                f"{self.outlier_min_m} and {self.outlier_max_m}"
            )

    @property
    def active(self) -> bool:
        """Whether these parameters change anything."""
        return self.features_per_scan > 0 or self.outlier_fraction > 0.0


def spurious_feature(
    rng: np.random.Generator, laser: LaserParams, p: ClutterParams
) -> ExtractedFeature:
    """One spurious detection in the sensor frame (true id −1): a circle with
    probability ``p.circle_fraction``, else a wall segment facing the sensor, uniform
    in bearing over the field of view and in range up to ``p.max_range_m``."""
    half_fov = 0.5 * laser.fov_rad
    b = rng.uniform(-half_fov, half_fov)
    r = rng.uniform(1.0, min(p.max_range_m, laser.max_range_m))
    x, y = r * math.cos(b), r * math.sin(b)
    if rng.random() < p.circle_fraction:
        radius = rng.uniform(0.1, 0.8)
        cov = np.diag([_CIRCLE_SIGMA_M**2, _CIRCLE_SIGMA_M**2, _CIRCLE_SIGMA_R_M**2])
        return ExtractedFeature(
            FeatureKind.CIRCLE, np.array([x, y, radius]), cov, -1, 7, (math.nan, math.nan)
        )
    th = rng.uniform(-math.pi, math.pi)
    # SPmap convention of extraction: the line's y axis (its normal) points to the sensor.
    if -math.sin(th) * (-x) + math.cos(th) * (-y) < 0.0:
        th = math.atan2(math.sin(th + math.pi), math.cos(th + math.pi))
    length = rng.uniform(2.0, 12.0)
    R = rot2(th)
    cov = np.zeros((3, 3))
    cov[:2, :2] = R @ np.diag([length**2 / 12.0, _LINE_SIGMA_LAT_M**2]) @ R.T
    cov[2, 2] = _LINE_SIGMA_THETA_RAD**2
    n_points = max(3, int(length / 0.25))
    return ExtractedFeature(
        FeatureKind.LINE, np.array([x, y, th]), cov, -1, n_points, (-length / 2, length / 2)
    )


def _displaced(rng: np.random.Generator, f: ExtractedFeature, p: ClutterParams) -> ExtractedFeature:
    d = rng.uniform(p.outlier_min_m, p.outlier_max_m)
    if f.kind == FeatureKind.LINE:
        a = float(f.params[2]) + math.pi / 2 + (math.pi if rng.random() < 0.5 else 0.0)
    else:
        a = rng.uniform(-math.pi, math.pi)
    moved = f.params.copy()
    moved[0] += d * math.cos(a)
    moved[1] += d * math.sin(a)
    return replace(f, params=moved)


def add_clutter(
    results: list[ExtractionResult],
    laser: LaserParams,
    params: ClutterParams,
    rng: np.random.Generator,
) -> list[ExtractionResult]:
    """``results`` (one per scan, in step order) with outliers and clutter applied.

    Per scan, in order: one uniform draw per real feature decides whether it is an
    outlier (and its displacement is drawn), then the spurious features are drawn
    and appended after the real ones.
    """
    out = []
    for res in results:
        feats = []
        for f in res.features:
            if params.outlier_fraction > 0.0 and rng.random() < params.outlier_fraction:
                f = _displaced(rng, f, params)
            feats.append(f)
        feats.extend(spurious_feature(rng, laser, params) for _ in range(params.features_per_scan))
        out.append(replace(res, features=tuple(feats)))
    return out
