"""Settings of known-map change detection: :class:`ChangeParams`."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from scipy.stats import chi2, norm

from mapfuse_core.perception.extraction import ExtractionParams
from mapfuse_core.sensor import LaserParams

__all__ = ["ChangeParams"]


@dataclass(frozen=True)
class ChangeParams:
    """Test level, view model and search limits of :func:`classify_changes`."""

    level: float = 0.999
    """Probability of the χ² test: a consistent feature is called moved with
    probability ``1 − level`` (lines 2 dof, circles 3 dof)."""
    min_obs: int = 3
    """Observations a landmark needs to count (as observed, as new, as a move target)."""
    min_scans: int = 20
    """``K``: scans a known feature must be predicted in view before, never associated,
    it is called missing (counted at every :attr:`view_stride`-th step, times the stride)."""
    view_stride: int = 4
    """Every this many steps the view is predicted (ray casting costs)."""
    laser: LaserParams | None = None
    """The scanner the log was recorded with.  Given, a feature is in view in a scan when
    the extractor (:attr:`extraction`) returns it from the noise-free scan that this
    laser would record of the map from the estimated pose: the extractor's own rules
    (points, length, incidence, a circle's predicted signal-to-noise) decide, within
    :attr:`max_range_m`, and the beam-count rule below is not used.  ``None``: the beam-count
    rule with :attr:`fov_rad`, :attr:`n_beams` and :attr:`max_range_m` (for logs whose
    features come from another detector, e.g. the car park's beacon poles)."""
    extraction: ExtractionParams | None = None
    """The extractor's settings for :attr:`laser` (default ``ExtractionParams()``, the
    simulator's)."""
    min_beams_line: int = 12
    """Beams that must hit a wall, at an incidence below :attr:`max_incidence_rad`,
    for the wall to count as in view in a scan (the extractor's least line support)."""
    min_beams_circle: int = 12
    """Beams that must hit a circle for it to count as in view in a scan."""
    min_beams_present: int = 3
    """Raw-scan beams aimed at a known circle's mapped disc that must return from within
    reach of it for a scan to see the circle still standing there
    (:func:`~mapfuse_core.changes.freespace.circles_seen_occupied`).  A
    circle seen so in more scans than seen empty, and in as many as a link needs
    (:attr:`link_min_scans`, at most :attr:`min_scans`), counts as seen for a link
    and is not linked to a landmark out of that reach: the trunk the beams hit is the
    tree itself, standing where surveyed (the extractor missed it; the landmark out of
    reach is another tree) or moved by less than the reach (and then hiding its own
    surveyed place from the view model).  Seen so in :attr:`min_scans` scans, it is
    not called missing."""
    max_incidence_rad: float = 1.3
    """Beams hitting a wall farther than this from its normal do not count (grazing
    beams give no extractable line)."""
    fov_rad: float = math.pi
    """Field of view of the scanner the view is predicted with."""
    n_beams: int = 361
    """Beams over the field of view in the predicted view."""
    max_range_m: float = 30.0
    """Range within which a feature counts as in view, under either rule.  Beyond it,
    features the map does not hold (trees too far to be extracted, so never mapped)
    may hide the feature or split it into pieces the extractor rejects, so not seeing
    it there says little."""
    missing_radius_sigmas: float | None = None
    """A circle is called missing only when it would have been extracted with its radius
    this many of the map's own radius σ smaller than mapped (``None``: the one-sided
    normal quantile of :attr:`level`, 3.09 at 0.999).  A map that draws a trunk too
    thick predicts it extractable where the real, thinner trunk is not, and its absence
    from the scans would then be taken for a removal; the margin asks the view to hold
    for any radius the map's error allows.  Moves and the other classes use the mapped
    radius."""
    max_move_m: float = 6.0
    """Farthest a known feature is looked for when no landmark is associated with it
    (widened by three of the feature's own position σ)."""
    max_turn_rad: float = 0.35
    """Largest turn of a line considered a move of that line (widened by three of the
    line's own angle σ)."""
    link_unviewed_lines: bool = True
    """Look for a moved wall even when its surveyed place was in view or seen empty for
    fewer than :attr:`link_min_scans` scans.  A wall is told apart by its direction and
    its extent: an unassociated landmark within :attr:`max_move_m` and
    :attr:`max_turn_rad` of it that also overlaps it along its length is that wall
    moved far more often than a wall the map lacks (circles:
    :attr:`link_unviewed_circles`).  A wall
    surveyed where the view model cannot see it (its mapped angle off enough to turn
    the scanner's view into a grazing one) is otherwise never linked to where it
    stands."""
    link_min_scans: int | None = 8
    """Scans a known feature without an associated landmark must be predicted in view
    at its surveyed place (or seen empty there) before an unassociated landmark within
    the move limits is taken for its move, counted like :attr:`min_scans` (``None``, or
    more than :attr:`min_scans`: :attr:`min_scans`, so that a feature seen long enough
    to be called missing is always looked for).  Calling a feature missing needs ``K``
    scans of its absence; a
    link has the landmark as evidence besides, so it asks for fewer: two of the view's
    sampled poses at the default stride.  A tree moved out of the scanner's reach often
    had its surveyed place in view only briefly (docs/results/changes.md)."""
    link_unviewed_circles: bool = False
    """Look for a moved circle even when its surveyed place was in view or seen empty for
    fewer than :attr:`link_min_scans` scans: the nearest unassociated circle within
    :attr:`max_move_m`, one to
    one, is taken for it.  Off by default: only distance (and a radius the map knows to
    its σ) relates the two, and an unmapped tree a few metres from a mapped one that
    was never in view is then called that tree's move instead of new."""

    free_space: bool = True
    """Read the log's raw scans, when it has them, for where the laser saw through a
    known circle's or wall's surveyed place
    (:mod:`mapfuse_core.changes.freespace`).  A feature seen empty counts
    as seen where the map has it, whatever the extractor's rule predicts: for
    :attr:`link_min_scans` scans it is linked to a landmark that moved, for
    :attr:`min_scans` it is otherwise called missing.  ``False``: the extractor's (or
    beam-count) rule alone."""

    relocalize: bool = True
    """Re-place a filter's poses from before its map match on the known map, from their
    steps' observations of landmarks the run merged with known features
    (:mod:`mapfuse_core.changes.relocalize`), before testing and predicting
    the view through them.  Only the steps a caller marks as estimated before the match
    are touched (a smoothed track has none).  ``False``: those poses enter with the
    anchor's covariance added, as filtered."""

    filter_estimates: bool = True
    """Test a landmark the estimator kept apart from the known map, and saw only before
    its match, through the estimator's own final estimate of it when one is given
    (``classify_changes(..., landmark_estimates=)``), its covariance scaled by the
    observations' spread factor.  ``False``: through its observations, as any other.
    The estimate is as trustworthy as the run is consistent: on a run metres off with
    NEES far above its dimension it adds false moves (``docs/results/carmen.md``)."""

    def __post_init__(self) -> None:
        if not 0.0 < self.level < 1.0:
            raise ValueError(f"ChangeParams.level must be in (0, 1), got {self.level}")
        for name in (
            "min_obs",
            "min_scans",
            "view_stride",
            "min_beams_line",
            "min_beams_circle",
            "min_beams_present",
            "n_beams",
        ):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"ChangeParams.{name} must be an int >= 1, got {v!r}")
        lm = self.link_min_scans
        if lm is not None and (isinstance(lm, bool) or not isinstance(lm, int) or lm < 1):
            raise ValueError(f"ChangeParams.link_min_scans must be None or an int >= 1, got {lm!r}")
        for name in (
            "link_unviewed_lines",
            "link_unviewed_circles",
            "free_space",
            "relocalize",
            "filter_estimates",
        ):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"ChangeParams.{name} must be a bool, got {getattr(self, name)!r}")
        m = self.missing_radius_sigmas
        if m is not None and not (
            isinstance(m, int | float) and not isinstance(m, bool) and math.isfinite(m) and m >= 0.0
        ):
            raise ValueError(
                "ChangeParams.missing_radius_sigmas must be a finite number >= 0 or None, "
                f"got {m!r}"
            )
        if self.n_beams < 2:
            raise ValueError(f"ChangeParams.n_beams must be >= 2, got {self.n_beams}")
        for name in ("max_incidence_rad", "fov_rad", "max_range_m", "max_move_m", "max_turn_rad"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0.0):
                raise ValueError(f"ChangeParams.{name} must be a finite number > 0, got {v!r}")
        if self.fov_rad > 2.0 * math.pi:
            raise ValueError(f"ChangeParams.fov_rad must be <= 2π, got {self.fov_rad}")
        if self.laser is not None and not isinstance(self.laser, LaserParams):
            raise ValueError(
                f"ChangeParams.laser must be a LaserParams or None, got {type(self.laser).__name__}"
            )
        if self.extraction is not None and not isinstance(self.extraction, ExtractionParams):
            raise ValueError(
                "ChangeParams.extraction must be an ExtractionParams or None, got "
                f"{type(self.extraction).__name__}"
            )

    def with_sensor(
        self, laser: LaserParams, extraction: ExtractionParams | None = None
    ) -> ChangeParams:
        """These settings with the view predicted by ``laser`` and its extractor."""
        return dataclasses.replace(self, laser=laser, extraction=extraction)

    def radius_margin_sigmas(self) -> float:
        """:attr:`missing_radius_sigmas`, or its default from :attr:`level`."""
        if self.missing_radius_sigmas is not None:
            return float(self.missing_radius_sigmas)
        return float(norm.ppf(self.level))

    def threshold(self, dof: int) -> float:
        """χ² threshold of the test with ``dof`` degrees of freedom."""
        return float(chi2.ppf(self.level, dof))
