"""Line and circle extraction from a laser scan, with honest first-order covariances.

Pipeline (all geometry is in the sensor frame ``S`` of the scan):

1. **Segmentation** into clusters of consecutive returns; a missing return or a gap
   between neighbouring points larger than ``jump_abs_m + jump_beams · ρ · Δβ``
   (an occlusion edge) starts a new cluster.  ``end_trim`` returns are dropped at
   both ends of each cluster.
2. **Circle or line**, from geometry only.  A short cluster, not cut by the edge of
   the field of view, is a circle candidate when it has at least as many returns as
   the smallest cluster at its range whose silhouette-filling circle would be well
   determined by its ranges (predicted ``r / σ_r ≥ min_circle_snr``, from the beam
   geometry alone); it is a circle when a weighted circle fit of its non-grazing beams
   passes a χ² test, has its centre behind the arc and does not contradict the beams
   beside the cluster (which must not cross it).  The laser's ``hit_ids`` are used
   only afterwards, to label a feature with the world id of most of its points.
3. **Lines**: split-and-merge (iterative end-point fit with noise-scaled tolerances,
   then merging of neighbours whose joint fit passes a χ² test) and a weighted
   total-least-squares fit in normal form ``(ρ, α)`` per segment, refined by
   Gauss–Newton on the measured ranges; covariance from the Gauss–Newton normal
   matrix; SPmap frame from :func:`mapfuse_core.geometry.features.line_from_normal` at the
   segment midpoint.
4. **Circles**: Levenberg–Marquardt (MINPACK's ``lmder``, see
   :func:`~mapfuse_core.perception.extraction.circles._levenberg_marquardt`) on ``‖p_i − c‖ − r``
   weighted by ``1 / nᵢᵀΣᵢnᵢ`` for the decision, refined by Levenberg–Marquardt on the
   measured ranges of the central beams and on the silhouette's edges (where the
   beams stop hitting the trunk); covariance ``(Jᵀ W J)⁻¹``, then both corrected for
   the detection rule.

Noise model (that of :mod:`mapfuse_core.sim.laser`): a return at nominal bearing ``β``
has range ``ρ(β + δβ) + δρ``, independent between beams.  Its point covariance is
``Σ_i = J diag(σρ², σβ²) Jᵀ``, so a residual along a unit normal ``n`` has variance
``nᵀΣᵢn = σρ² (n·u)² + ρ² σβ² (n·u⊥)²`` (``u`` the beam direction); this weights the
point-space fits.  The final fits work on the ranges themselves: the predicted mean
is ``ρ̂ + ½ ρ̂'' σβ²`` and the variance ``σρ² + ρ̂'² σβ² + ½ ρ̂''² σβ⁴``, with ``ρ̂'``,
``ρ̂''`` the derivatives of the predicted range w.r.t. the bearing.

Why the refinement in range space: the Jacobian of a point-space residual
(``p_i·t`` for a line, the normal at ``p_i`` for a circle) contains the noise of the
point itself, and range noise moves a point along and across the curve at once; the
correlation between Jacobian and residual biases the estimate (errors in variables).
On a trunk, whose radius is known only to about a tenth, the bias is a large fraction
of σ on the radius (``docs/results/extraction.md``).  In range space the Jacobian depends only
on the beam and the parameters, and the bias is gone.

What else keeps the covariances honest (checked by
``tests/test_extraction_consistency.py``) is leaving out data the first-order model
does not describe, with rules computable without the truth:

* returns within ``Δβ + corner_margin_sigma · σβ`` of a split point (a corner) may
  come from the other wall and are dropped from both segments; end returns of a line
  with a normalised residual above ``end_outlier_sigma`` are peeled off (a corner
  too close to a cluster end for the split to see);
* a cluster end next to a *nearer* return (an occluder, e.g. a trunk in front of a
  building) may hide a corner: the adjoining wall can show as a stub of one or two
  returns, too short for the split, and a ray cast near the hidden corner can cross
  it, so its range comes from the other wall.  Line fits drop the returns within
  ``corner_margin_sigma · σβ`` of such an end (``occluded_end_margin``; its effect
  on loop600 is in ``docs/results/extraction.md``);
* the outermost return of a cluster is there *because* its perturbed ray still hits
  the feature, which conditions its bearing error (``end_trim``);
* grazing returns are dropped (incidence above ``max_line_incidence_rad`` /
  ``max_circle_incidence_rad``, or, on circles, a range too nonlinear in the bearing
  error: ``max_range_nonlinearity``);
* which clusters may be circles, and which of their beams are fitted, is decided from
  the bearings of the cluster, never from the fitted radius: selecting on the fitted
  radius or its σ keeps the noise realisations that look most curved, which biases
  the radius of small trunks by σ's (``docs/results/extraction.md``);
* a circle's radius comes mostly from its silhouette.  The ranges of a short arc fix
  it only through the arc's curvature: such a fit errs outwards by a fifth of its σ,
  and its covariance, taken at the fitted circle, shrinks as the fitted radius does,
  so its whitened errors leaned −0.15 σ to −0.4 σ.  The bearings where the beams stop
  hitting the trunk read its angular width ``2 asin(r / D)`` to a fraction of a beam
  spacing (:func:`~mapfuse_core.perception.extraction.noise._edge_moments`): with them
  in the fit the radius is known several times better and its covariance no longer
  follows its error.  Two things keep that unbiased.  The ranges fitted are those of
  a fixed number of central beams, the number every detectable cluster at that range
  has: fitting all of a cluster's beams makes the fit's gain on the width depend on
  the width read, which biased the radius by −0.07 σ.  And the size a cluster needs to
  be tried as a circle is a bound on the width read, so near it only the trunks that
  read wide are seen; the fit subtracts that excess, to first order, and widens or
  narrows its covariance to match (``docs/results/extraction.md``: about half of the bias is
  left where half the clusters are detected);
* a circle whose silhouette a beam beside the cluster crosses is not a trunk, but only
  a crossing deeper than 3 σ of the fit counts
  (:func:`~mapfuse_core.perception.extraction.circles._crosses_silhouette`): testing the fitted
  circle itself would reject the fits whose radius comes out too large;
* every fit must pass a χ² test on its normalised residuals.

The 3×3 covariance of a line holds, along the line, the pseudo-variance ``L²/12`` of
a position uniform over the observed segment of length ``L``.  It never reaches a
residual when the observed line is the *first* argument of
:func:`mapfuse_core.models.dispatch.line_pairing` (as in
:func:`mapfuse_core.models.dispatch.observe`): that Jacobian has no along-line component.
As the second argument it would leak ``(L²/12) sin²Δθ`` into the lateral variance.

Modules: :mod:`~mapfuse_core.perception.extraction.params` (thresholds, features, result),
:mod:`~mapfuse_core.perception.extraction.noise` (noise model, χ² bound),
:mod:`~mapfuse_core.perception.extraction.segment` (clusters, occluded ends),
:mod:`~mapfuse_core.perception.extraction.lines` (split-and-merge, line fits),
:mod:`~mapfuse_core.perception.extraction.circles` (circle candidates and fits),
:mod:`~mapfuse_core.perception.extraction.labels` (world-id labels) and
:mod:`~mapfuse_core.perception.extraction.extract` (:func:`extract_features`).  Measured effects of
the rules above are in ``docs/results/extraction.md``.
"""

from mapfuse_core.perception.extraction.circles import _beam_cos_inc as _beam_cos_inc
from mapfuse_core.perception.extraction.circles import _candidate_beams as _candidate_beams
from mapfuse_core.perception.extraction.circles import _circle_system as _circle_system
from mapfuse_core.perception.extraction.circles import (
    _detection_correction as _detection_correction,
)
from mapfuse_core.perception.extraction.circles import _Edges as _Edges
from mapfuse_core.perception.extraction.circles import _geometric_circle as _geometric_circle
from mapfuse_core.perception.extraction.circles import _kasa as _kasa
from mapfuse_core.perception.extraction.circles import _refine_circle as _refine_circle
from mapfuse_core.perception.extraction.circles import (
    _silhouette_candidates as _silhouette_candidates,
)
from mapfuse_core.perception.extraction.extract import extract_features
from mapfuse_core.perception.extraction.noise import _edge_moments as _edge_moments
from mapfuse_core.perception.extraction.noise import _Noise as _Noise
from mapfuse_core.perception.extraction.noise import _normal_var as _normal_var
from mapfuse_core.perception.extraction.params import (
    EXTRACTION_PROFILES,
    ExtractedFeature,
    ExtractionParams,
    ExtractionResult,
)

__all__ = [
    "EXTRACTION_PROFILES",
    "ExtractedFeature",
    "ExtractionParams",
    "ExtractionResult",
    "extract_features",
]
