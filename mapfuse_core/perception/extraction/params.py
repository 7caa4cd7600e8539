"""Parameters of the feature extraction and the features and tallies it returns.

The rules these thresholds control are explained in the package docstring of
:mod:`mapfuse_core.perception.extraction`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["EXTRACTION_PROFILES", "ExtractedFeature", "ExtractionParams", "ExtractionResult"]


@dataclass(frozen=True)
class ExtractionParams:
    """Thresholds of the feature extraction; defaults suit the paper's laser (Table 1)."""

    jump_abs_m: float = 0.3
    """Absolute part of the gap between neighbouring points that splits a cluster (m);
    about 4σ of the difference of two range errors, so noise alone rarely splits."""
    jump_beams: float = 4.0
    """Range-proportional part of the split gap, in beam spacings at the nearer range:
    a wall seen at incidence γ has points ``ρΔβ / cos γ`` apart, so 4 keeps walls up
    to γ ≈ 75° in one cluster."""
    end_trim: int = 1
    """Returns dropped at each end of every cluster (conditioned bearing error)."""
    min_line_points: int = 8
    """Minimum number of points a line is fitted to, after trimming."""
    min_line_length_m: float = 2.5
    """Minimum length of an accepted line (m).  Keep it above the diameter of the
    largest trunk in the world (2 m for radii up to 1 m): the arc of a trunk too small
    or too far to be fitted as a circle has so little curvature that it would pass the
    line fit."""
    split_tol_abs_m: float = 0.10
    """Floor of the split-and-merge tolerance on the distance to the chord (m)."""
    split_tol_sigma: float = 4.0
    """Split-and-merge tolerance in standard deviations of the point's error normal to
    the chord; the larger of this and the floor is used."""
    corner_margin_sigma: float = 4.0
    """Points whose bearing is within ``Δβ + corner_margin_sigma · σβ`` of a split
    point are dropped from both segments (they may belong to the other wall)."""
    max_line_incidence_rad: float = math.radians(80.0)
    """Returns hitting a line at a larger incidence angle (beam vs normal) are dropped."""
    end_outlier_sigma: float = 3.0
    """An end return of a line whose normalised range residual exceeds this is dropped
    and the line refitted (it likely lies on the wall round an unseen corner)."""
    max_end_outliers: int = 3
    """At most this many returns are peeled off each end of a line that way."""
    occluded_end_margin: bool = True
    """Whether line fits drop the returns within ``corner_margin_sigma · σβ`` of a
    cluster end whose neighbouring return is nearer (a possibly hidden corner; see the
    package docstring of :mod:`mapfuse_core.perception.extraction`).  Decided from ranges and
    bearings alone, so it selects no noise realisation."""
    min_circle_points: int = 5
    """Minimum number of central (non-grazing) points a circle is fitted to."""
    circle_radius_min_m: float = 0.05
    """Smallest accepted circle radius (m)."""
    circle_radius_max_m: float = 2.0
    """Largest accepted circle radius (m); clusters wider than ``2.2 ×`` this are never
    tried as circles.  Keep it several σ_r above the largest real radius (1 m) so that
    the bound does not cut the upper tail of the radius estimates."""
    max_circle_incidence_rad: float = math.radians(60.0)
    """Beams hitting a circle at a larger incidence angle are not fitted (grazing)."""
    max_range_nonlinearity: float = 0.1
    """Circle returns whose range is too nonlinear in the bearing error are dropped:
    the standard deviation of ``½ ρ'' δβ²`` must not exceed this fraction of the range
    standard deviation.  Near the silhouette of a small, far trunk this bites well
    before ``max_circle_incidence_rad``."""
    min_circle_snr: float = 4.0
    """A short cluster is tried as a circle only if it has at least as many returns as
    the smallest cluster at its range whose silhouette-filling circle would give a fit
    to the ranges alone ``r / σ_r`` at least this large, predicted from the beam
    geometry alone (see
    :func:`~mapfuse_core.perception.extraction.circles._silhouette_candidates`).  At 4
    the ranges alone know the radius to 25 %; the fit adds the silhouette, so this sets
    how far trunks are seen rather than how well they are measured."""
    max_circle_radius_rel_sigma: float = 0.5
    """Sanity bound: circles whose fitted σ_r exceeds this fraction of the radius are
    rejected (``ill_conditioned``); not reached after ``min_circle_snr`` unless the fit
    went wrong."""
    chi2_quantile: float = 0.999
    """A fit is accepted when its residual χ² is below this quantile of χ²(n − p)."""
    label_majority: float = 0.8
    """Fraction of points from one world id needed to label ``true_id`` (else −1)."""
    weight_iterations: int = 3
    """Re-weighting passes of the line fit (the weights depend on the normal)."""
    sigma_floor_m: float = 1e-6
    """Floor on a point's residual standard deviation (m), so that a noise-free laser
    still gives finite weights; far below any real noise."""
    wall_roughness_m: float = 0.0
    """σ (m) of how far a real surface departs from its fitted line at one return
    (plaster, skirting boards, door frames), added in quadrature to the laser's σρ in
    every fit.  0 for the simulated worlds, whose walls are exact segments."""
    line_model_sigma_m: float = 0.0
    """σ (m) added to every line's ρ: the part of a real wall's deviation from a
    straight line that is common to all returns of one segment (a bowed wall seen over
    part of its length), which no number of returns averages out."""
    line_model_sigma_rad: float = 0.0
    """σ (rad) added to every line's α, for the same reason as :attr:`line_model_sigma_m`."""

    def __post_init__(self) -> None:
        if not isinstance(self.occluded_end_margin, bool):
            raise ValueError("ExtractionParams.occluded_end_margin must be a bool")
        for name, value in self.__dict__.items():
            if name == "occluded_end_margin":
                continue
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise ValueError(f"ExtractionParams.{name} must be a number, got {value!r}")
            if not math.isfinite(value):
                raise ValueError(f"ExtractionParams.{name} must be finite, got {value}")
            if value < 0:
                raise ValueError(f"ExtractionParams.{name} must be >= 0, got {value}")
        for name in (
            "end_trim",
            "min_line_points",
            "min_circle_points",
            "weight_iterations",
            "max_end_outliers",
        ):
            if not isinstance(getattr(self, name), int):
                raise ValueError(f"ExtractionParams.{name} must be an integer")
        if self.min_line_points < 3:
            raise ValueError("ExtractionParams.min_line_points must be >= 3")
        if self.min_circle_points < 4:
            raise ValueError("ExtractionParams.min_circle_points must be >= 4")
        if self.weight_iterations < 1:
            raise ValueError("ExtractionParams.weight_iterations must be >= 1")
        if not self.circle_radius_min_m < self.circle_radius_max_m:
            raise ValueError("ExtractionParams.circle_radius_min_m must be < circle_radius_max_m")
        if not 0.0 < self.chi2_quantile < 1.0:
            raise ValueError("ExtractionParams.chi2_quantile must be in (0, 1)")
        if not 0.5 < self.label_majority <= 1.0:
            raise ValueError("ExtractionParams.label_majority must be in (0.5, 1]")
        if self.sigma_floor_m <= 0.0:
            raise ValueError("ExtractionParams.sigma_floor_m must be > 0")
        for name in ("max_line_incidence_rad", "max_circle_incidence_rad"):
            if not 0.0 < getattr(self, name) <= math.pi / 2:
                raise ValueError(f"ExtractionParams.{name} must be in (0, π/2]")

    @classmethod
    def indoor_sick(cls) -> ExtractionParams:
        """Thresholds for a 1° or 0.5° SICK scanner indoors (``docs/real-data.md``).

        Rooms a few metres across: walls of 0.5–1 m between doors and furniture,
        returns 1–10 cm apart, no trunks (circles off), and plaster walls that are not
        flat to the laser's σρ, hence the roughness and line model-error terms,
        estimated on the Intel and CSAIL logs against their floor plans.
        """
        return cls(
            jump_abs_m=0.20,
            jump_beams=8.0,
            end_trim=1,
            min_line_points=5,
            min_line_length_m=0.4,
            split_tol_abs_m=0.04,
            split_tol_sigma=4.0,
            max_end_outliers=3,
            min_circle_points=10_000,
            wall_roughness_m=0.01,
            line_model_sigma_m=0.02,
            line_model_sigma_rad=math.radians(0.8),
        )

    @classmethod
    def profile(cls, name: str) -> ExtractionParams:
        """The named profile: one of :data:`EXTRACTION_PROFILES`."""
        if name == "default":
            return cls()
        if name == "indoor_sick":
            return cls.indoor_sick()
        raise ValueError(
            f"unknown extraction profile {name!r}; known: {', '.join(EXTRACTION_PROFILES)}"
        )


EXTRACTION_PROFILES: tuple[str, ...] = ("default", "indoor_sick")
"""Names :meth:`ExtractionParams.profile` accepts: ``default`` (the simulated laser of
the paper's Table 1) and ``indoor_sick`` (:meth:`ExtractionParams.indoor_sick`)."""


@dataclass(frozen=True)
class ExtractedFeature:
    """A line or circle observed in one scan, in the sensor frame."""

    kind: FeatureKind
    """Feature type."""
    params: FloatArray
    """(3,) SPmap line ``(x, y, θ)`` at the segment midpoint, y axis towards the sensor,
    or circle ``(x, y, r)``; sensor frame."""
    cov: FloatArray
    """(3, 3) covariance of :attr:`params`.  For a line the along-line direction holds a
    pseudo-variance ``L²/12`` (``L`` the segment length, the variance of a uniform
    position along the segment): it lets association compare along-line positions
    loosely and has no effect on the pairing residual when the observed line is its
    first argument (as in :func:`mapfuse_core.models.dispatch.observe`)."""
    true_id: int
    """World id that produced at least ``label_majority`` of the points, −1 if none."""
    n_points: int
    """Number of laser points the feature was fitted to."""
    extent: tuple[float, float]
    """Lines: along-line coordinates (m, along the frame's x axis) of the first and last
    fitted points relative to the :attr:`params` origin, ``extent[0] ≤ extent[1]``;
    circles: ``(nan, nan)``."""


@dataclass(frozen=True)
class ExtractionResult:
    """Features accepted from one scan and the tally of what was rejected."""

    features: tuple[ExtractedFeature, ...]
    """Accepted features, in scan order."""
    rejected: dict[str, int] = field(default_factory=dict)
    """Reason → number of clusters or segments rejected for it."""
