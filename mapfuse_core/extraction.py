"""Line and circle extraction from a laser scan, with honest first-order covariances.

Pipeline (all geometry is in the sensor frame ``S`` of the scan):

1. **Segmentation** into clusters of consecutive returns; a missing return or a gap
   between neighbouring points larger than ``jump_abs_m + jump_beams · ρ · Δβ``
   (an occlusion edge) starts a new cluster.  ``end_trim`` returns are dropped at
   both ends of each cluster.
2. **Circle or line**, from geometry only.  A short cluster, not cut by the edge of
   the field of view, is a circle candidate when a circle filling its bearing span
   would be well determined (predicted ``r / σ_r ≥ min_circle_snr``, from the beam
   geometry alone); it is a circle when a weighted circle fit of its central beams
   passes a χ² test, has its centre behind the arc and does not contradict the beams
   beside the cluster (which must not cross it).  The laser's ``hit_ids`` are used
   only afterwards, to label a feature with the world id of most of its points.
3. **Lines**: split-and-merge (iterative end-point fit with noise-scaled tolerances,
   then merging of neighbours whose joint fit passes a χ² test) and a weighted
   total-least-squares fit in normal form ``(ρ, α)`` per segment, refined by
   Gauss–Newton on the measured ranges; covariance from the Gauss–Newton normal
   matrix; SPmap frame from :func:`mapfuse_core.features.line_from_normal` at the
   segment midpoint.
4. **Circles**: Levenberg–Marquardt (MINPACK's ``lmder``, see :func:`_levenberg_marquardt`)
   on ``‖p_i − c‖ − r`` weighted by ``1 / nᵢᵀΣᵢnᵢ`` for the decision, refined by
   Levenberg–Marquardt on the measured ranges; covariance ``(Jᵀ W J)⁻¹``.

Noise model (that of :mod:`mapfuse_core.laser`): a return at nominal bearing ``β``
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
of σ on the radius (``docs/extraction.md``).  In range space the Jacobian depends only
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
  on loop600 is in ``docs/extraction.md``);
* the outermost return of a cluster is there *because* its perturbed ray still hits
  the feature, which conditions its bearing error (``end_trim``);
* grazing returns are dropped (incidence above ``max_line_incidence_rad`` /
  ``max_circle_incidence_rad``, or, on circles, a range too nonlinear in the bearing
  error: ``max_range_nonlinearity``);
* which clusters may be circles, and which of their beams are fitted, is decided from
  the bearings of the cluster, never from the fitted radius: selecting on the fitted
  radius or its σ keeps the noise realisations that look most curved, which biases
  the radius of small trunks by σ's (``docs/extraction.md``);
* a circle whose silhouette a beam beside the cluster crosses is not a trunk, but only
  a crossing deeper than 3 σ of the fit counts (:func:`_crosses_silhouette`): testing
  the fitted circle itself would reject the fits whose radius comes out too large;
* every fit must pass a χ² test on its normalised residuals.

The 3×3 covariance of a line holds, along the line, the pseudo-variance ``L²/12`` of
a position uniform over the observed segment of length ``L``.  It never reaches a
residual when the observed line is the *first* argument of
:func:`mapfuse_core.features.line_pairing` (as in
:func:`mapfuse_core.features.observe`): that Jacobian has no along-line component.
As the second argument it would leak ``(L²/12) sin²Δθ`` into the lateral variance.
"""

from __future__ import annotations

import functools
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import leastsq
from scipy.stats import chi2 as chi2_dist

from mapfuse_core.features import FeatureKind, line_from_normal
from mapfuse_core.laser import LaserParams, Scan
from mapfuse_core.se2 import FloatArray

__all__ = ["ExtractedFeature", "ExtractionParams", "ExtractionResult", "extract_features"]


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
    module docstring).  Decided from ranges and bearings alone, so it selects no noise
    realisation."""
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
    """A short cluster is tried as a circle only if a circle filling its bearing span
    would have ``r / σ_r`` at least this large, predicted from the beam geometry alone
    (see :func:`_circle_beams`).  At 4 the radius is known to 25 %; below about 3 the
    estimate is visibly non-Gaussian (heavier NEES tails)."""
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
    first argument (as in :func:`mapfuse_core.features.observe`)."""
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


# --------------------------------------------------------------------------- noise model


@dataclass(frozen=True)
class _Noise:
    """Laser noise as the fits need it."""

    var_r: float
    """σρ² (m²)."""
    var_b: float
    """σβ² (rad²)."""
    floor2: float
    """Variance floor (m²)."""


def _normal_var(noise: _Noise, rng_: FloatArray, cos_inc: FloatArray) -> FloatArray:
    """Variance of a point's offset along a unit normal at incidence ``inc`` to its beam.

    ``nᵀ Σ n`` with ``Σ = J diag(σρ², σβ²) Jᵀ``: the range error projects with
    ``cos inc`` and the cross-beam error ``ρ δβ`` with ``sin inc``.
    """
    c2 = cos_inc * cos_inc
    return noise.var_r * c2 + rng_ * rng_ * noise.var_b * (1.0 - c2) + noise.floor2


def _range_moments(noise: _Noise, d1: FloatArray, d2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Mean offset and variance of a measured range, given ``ρ'`` and ``ρ''`` of its beam.

    The measured range is ``ρ(β + δβ) + δρ ≈ ρ + ρ' δβ + ½ ρ'' δβ² + δρ`` at the nominal
    bearing ``β``: its mean is ``ρ + ½ ρ'' σβ²`` and its variance
    ``σρ² + ρ'² σβ² + ½ ρ''² σβ⁴``.
    """
    bias = 0.5 * d2 * noise.var_b
    var = noise.var_r + d1 * d1 * noise.var_b + 0.5 * d2 * d2 * noise.var_b**2 + noise.floor2
    return bias, var


def _nonlinearity(noise: _Noise, d2: FloatArray, var: FloatArray) -> FloatArray:
    """Standard deviation of the quadratic term ``½ ρ'' δβ²`` relative to the range's.

    Near a circle's silhouette ``ρ(β)`` bends sharply (``ρ''`` grows like
    ``D² / (r cos³γ)``), and the linearised model stops describing the range error long
    before the incidence angle looks extreme when the circle is far and small.
    """
    out: FloatArray = np.abs(d2) * noise.var_b / math.sqrt(2.0) / np.sqrt(var)
    return out


@functools.lru_cache(maxsize=4096)
def _chi2_quantile(q: float, dof: int) -> float:
    return float(chi2_dist.ppf(q, max(dof, 1)))


def _chi2_max(params: ExtractionParams, dof: int) -> float:
    """Acceptance bound on a fit's χ² with ``dof`` degrees of freedom."""
    return _chi2_quantile(params.chi2_quantile, dof)


def _gauss_newton_cov(J: FloatArray, w: FloatArray, max_cond: float) -> FloatArray | None:
    """``(Jᵀ W J)⁻¹``, or ``None`` when the normal matrix is (nearly) singular."""
    N = (w[:, None] * J).T @ J
    if not np.isfinite(N).all():
        return None
    ev = np.linalg.eigvalsh(N)
    if ev[0] <= 0.0 or ev[-1] > max_cond * ev[0]:
        return None
    cov = np.asarray(np.linalg.inv(N), dtype=np.float64)
    return 0.5 * (cov + cov.T)


def _median(a: FloatArray) -> float:
    """``np.median`` of a finite 1-D array, bit for bit, without its generality and cost."""
    s = np.sort(a)
    m = s.size // 2
    return float(s[m]) if s.size % 2 else float((s[m - 1] + s[m]) / 2.0)


def _min_normal(S: FloatArray) -> FloatArray:
    """Unit eigenvector of the smaller eigenvalue of a symmetric 2×2 scatter matrix."""
    # The major axis of [[a, b], [b, c]] is at ½ atan2(2b, a − c); the normal is ⊥ to it.
    phi = 0.5 * math.atan2(2.0 * S[0, 1], S[0, 0] - S[1, 1]) + 0.5 * math.pi
    return np.array([math.cos(phi), math.sin(phi)])


# --------------------------------------------------------------------------- lines


@dataclass(frozen=True)
class _LineFit:
    """A line fit in normal form."""

    rho: float
    """Distance ρ ≥ 0 of the line from the sensor (m)."""
    alpha: float
    """Direction α of the line's normal (rad)."""
    chi2: float
    """Sum of squared normalised residuals."""
    cos_inc: FloatArray
    """(n,) cosine of each beam's incidence angle on the line."""
    cov: FloatArray | None = None
    """(2, 2) covariance of ``(ρ, α)``; only from the range-space fit."""
    z: FloatArray | None = None
    """(n,) normalised range residuals; only from the range-space fit."""


def _tls_line(
    P: FloatArray, r: FloatArray, b: FloatArray, noise: _Noise, iters: int
) -> _LineFit | None:
    """Weighted total least squares in normal form (point space); ``None`` if degenerate.

    Minimises ``Σ (p_i·n − ρ)² / nᵀΣ_i n`` with the weights re-evaluated at the current
    normal.  Used for split-and-merge decisions and to start :func:`_refine_line`.
    """
    if P.shape[0] < 2:
        return None
    c = P.mean(axis=0)
    Q = P - c
    S = Q.T @ Q
    if S[0, 0] + S[1, 1] <= 1e-18:
        return None  # all points coincide
    nrm = _min_normal(S)
    for _ in range(iters):
        alpha = math.atan2(nrm[1], nrm[0])
        w = 1.0 / _normal_var(noise, r, np.cos(b - alpha))
        c = (w[:, None] * P).sum(axis=0) / w.sum()
        Q = P - c
        nrm = _min_normal((w[:, None] * Q).T @ Q)
    if float(c @ nrm) < 0.0:
        nrm = -nrm
    rho = float(c @ nrm)
    alpha = math.atan2(nrm[1], nrm[0])
    cos_inc = np.cos(b - alpha)
    res = P @ nrm - rho
    chi2 = float(np.sum(res * res / _normal_var(noise, r, cos_inc)))
    return _LineFit(rho, alpha, chi2, cos_inc)


def _refine_line(r: FloatArray, b: FloatArray, start: _LineFit, noise: _Noise) -> _LineFit | None:
    """Gauss–Newton fit of ``(ρ, α)`` to the measured *ranges*, from ``start``.

    Beam ``i`` at incidence ``γ_i = β_i − α`` predicts ``ρ̂_i = ρ / cos γ_i``, with the
    mean and variance of :func:`_range_moments` (``ρ̂' = ρ̂ tan γ``,
    ``ρ̂'' = ρ̂ (2 tan²γ + 1)``) and the Jacobian ``(1 / cos γ_i, −ρ̂_i tan γ_i)``.  The
    point-space residual ``p_i·n − ρ`` has the Jacobian ``p_i·t``, which carries the
    noise of ``p_i`` itself (range noise moves a point along and across the line at
    once): an errors-in-variables bias that this formulation does not have.
    ``None`` if a beam does not face the line or the normal matrix is singular.
    """
    rho, alpha = start.rho, start.alpha
    for _ in range(12):
        g = b - alpha
        cg = np.cos(g)
        if rho <= 0.0 or bool((cg <= 1e-3).any()):
            return None
        tg = np.tan(g)
        pred = rho / cg
        bias, var = _range_moments(noise, pred * tg, pred * (2.0 * tg * tg + 1.0))
        res = r - pred - bias
        w = 1.0 / var
        ja = 1.0 / cg
        jb = -pred * tg
        wa, wb = w * ja, w * jb
        n11, n12, n22 = float(wa @ ja), float(wa @ jb), float(wb @ jb)
        det = n11 * n22 - n12 * n12
        if not det > 1e-12 * n11 * n22:
            return None
        g1, g2 = float(wa @ res), float(wb @ res)
        d_rho = (n22 * g1 - n12 * g2) / det
        d_alpha = (n11 * g2 - n12 * g1) / det
        rho, alpha = rho + d_rho, alpha + d_alpha
        # Quadratic convergence: once the step is this small the normal matrix and
        # residuals above are those of the solution to far better than their noise.
        if abs(d_rho) < 1e-7 and abs(d_alpha) < 1e-9:
            break
    else:
        return None
    cov = np.array([[n22, -n12], [-n12, n11]]) / det
    alpha = math.atan2(math.sin(alpha), math.cos(alpha))
    z = res * np.sqrt(w)
    return _LineFit(rho, alpha, float(z @ z), np.cos(b - alpha), cov, z)


def _split(
    P: FloatArray, r: FloatArray, b: FloatArray, noise: _Noise, params: ExtractionParams
) -> list[tuple[int, int]]:
    """Iterative end-point fit: inclusive index ranges sharing their split points."""
    out: list[tuple[int, int]] = []
    stack = [(0, P.shape[0] - 1)]
    while stack:
        lo, hi = stack.pop()
        chord = P[hi] - P[lo]
        length = math.hypot(chord[0], chord[1])
        if hi - lo < 2 or length <= 1e-12:
            out.append((lo, hi))
            continue
        nrm = np.array([-chord[1], chord[0]]) / length
        inner = slice(lo + 1, hi)
        dist = np.abs((P[inner] - P[lo]) @ nrm)
        alpha = math.atan2(nrm[1], nrm[0])
        sig = np.sqrt(_normal_var(noise, r[inner], np.cos(b[inner] - alpha)))
        tol = np.maximum(params.split_tol_abs_m, params.split_tol_sigma * sig)
        k = int(np.argmax(dist / tol))
        if dist[k] > tol[k]:
            mid = lo + 1 + k
            stack.append((mid, hi))
            stack.append((lo, mid))
        else:
            out.append((lo, hi))
    out.sort()
    return out


def _merge(
    segs: list[tuple[int, int]],
    P: FloatArray,
    r: FloatArray,
    b: FloatArray,
    noise: _Noise,
    params: ExtractionParams,
) -> list[tuple[int, int]]:
    """Merge neighbouring segments, best first, while a joint line passes the χ² test."""
    segs = list(segs)
    while len(segs) > 1:
        best_k, best_score = -1, math.inf
        for k in range(len(segs) - 1):
            lo, hi = segs[k][0], segs[k + 1][1]
            sel = slice(lo, hi + 1)
            fit = _tls_line(P[sel], r[sel], b[sel], noise, 2)
            if fit is None:
                continue
            score = fit.chi2 / _chi2_max(params, hi - lo + 1 - 2)
            if score <= 1.0 and score < best_score:
                best_k, best_score = k, score
        if best_k < 0:
            break
        segs[best_k : best_k + 2] = [(segs[best_k][0], segs[best_k + 1][1])]
    return segs


def _line_feature(
    P: FloatArray,
    r: FloatArray,
    b: FloatArray,
    ids: np.ndarray,
    noise: _Noise,
    params: ExtractionParams,
) -> ExtractedFeature | str:
    """The line fitted to one segment, or the reason it was rejected."""
    if P.shape[0] < params.min_line_points:
        return "too_few_points"
    start = _tls_line(P, r, b, noise, params.weight_iterations)
    if start is None:
        return "degenerate"
    keep = np.abs(start.cos_inc) >= math.cos(params.max_line_incidence_rad)
    if not keep.all():
        P, r, b, ids = P[keep], r[keep], b[keep], ids[keep]
        if P.shape[0] < params.min_line_points:
            return "grazing"
    # Cheap early exit (most rejected segments are short); the exact test comes below.
    t_start = np.array([-math.sin(start.alpha), math.cos(start.alpha)])
    s_start = P @ t_start
    if float(s_start.max() - s_start.min()) < 0.9 * params.min_line_length_m:
        return "too_short"
    fit = _refine_line(r, b, start, noise)
    # A segment ending at a corner that the split could not see (the chord method never
    # tests its own end points) may end with returns from the other wall: peel off end
    # returns that the line does not explain.
    peeled = [0, 0]
    while fit is not None and fit.z is not None and P.shape[0] > params.min_line_points:
        bad = [
            abs(float(fit.z[i])) if n < params.max_end_outliers else 0.0
            for i, n in zip((0, -1), peeled, strict=True)
        ]
        end = 0 if bad[0] >= bad[1] else 1
        if bad[end] <= params.end_outlier_sigma:
            break
        peeled[end] += 1
        sel = slice(1, None) if end == 0 else slice(None, -1)
        P, r, b, ids = P[sel], r[sel], b[sel], ids[sel]
        fit = _refine_line(r, b, fit, noise)
    if fit is None or fit.cov is None:
        return "degenerate"
    n_pts = P.shape[0]
    if fit.chi2 > _chi2_max(params, n_pts - 2):
        return "poor_fit"
    tangent = np.array([-math.sin(fit.alpha), math.cos(fit.alpha)])
    s = P @ tangent
    s0, s1 = float(s.min()), float(s.max())
    length = s1 - s0
    if length < params.min_line_length_m:
        return "too_short"
    t_mid = 0.5 * (s0 + s1)
    line, J = line_from_normal(fit.rho, fit.alpha, t_mid)
    C = np.zeros((3, 3))
    C[:2, :2] = fit.cov
    C[2, 2] = length * length / 12.0
    cov = J @ C @ J.T
    return ExtractedFeature(
        kind=FeatureKind.LINE,
        params=line,
        cov=0.5 * (cov + cov.T),
        true_id=_label(ids, params.label_majority),
        n_points=n_pts,
        extent=(s0 - t_mid, s1 - t_mid),
    )


def _lines_from_cluster(
    P: FloatArray,
    r: FloatArray,
    b: FloatArray,
    ids: np.ndarray,
    noise: _Noise,
    laser: LaserParams,
    params: ExtractionParams,
    rejected: Counter[str],
) -> list[ExtractedFeature]:
    """Lines of one cluster (split-and-merge, corner margins); rejections are tallied."""
    segs = _merge(_split(P, r, b, noise, params), P, r, b, noise, params)
    # Round-off in the bearings must not decide whether a beam is inside the margin.
    margin = (laser.beam_spacing_rad + params.corner_margin_sigma * laser.sigma_bearing_rad) * (
        1.0 + 1e-9
    )
    out: list[ExtractedFeature] = []
    for k, (lo, hi) in enumerate(segs):
        sel = np.arange(lo, hi + 1)
        if k > 0:
            sel = sel[np.abs(b[sel] - b[lo]) > margin]
        if k < len(segs) - 1:
            sel = sel[np.abs(b[sel] - b[hi]) > margin]
        f = _line_feature(P[sel], r[sel], b[sel], ids[sel], noise, params)
        if isinstance(f, str):
            rejected[f] += 1
        else:
            out.append(f)
    return out


# --------------------------------------------------------------------------- circles


@dataclass(frozen=True)
class _CircleFit:
    """A circle fit."""

    x: FloatArray
    """(3,) centre and radius ``(cx, cy, r)``."""
    chi2: float
    """Sum of squared normalised residuals."""
    cos_inc: FloatArray
    """(n,) cosine of each beam's incidence angle on the circle (0 if it misses)."""
    cov: FloatArray | None = None
    """(3, 3) covariance of :attr:`x`; only from the range-space fit."""


def _kasa(P: FloatArray) -> FloatArray | None:
    """Algebraic circle fit (starting point); ``None`` for (nearly) collinear points."""
    m = P.mean(axis=0)
    Q = P - m  # centred, so that the conditioning reflects the shape, not the range
    A = np.column_stack((2.0 * Q, np.ones(P.shape[0])))
    sv = np.linalg.svd(A, compute_uv=False)
    if sv[-1] <= 1e-9 * sv[0]:
        return None
    sol = np.linalg.lstsq(A, np.sum(Q * Q, axis=1), rcond=None)[0]
    r2 = sol[2] + sol[0] ** 2 + sol[1] ** 2
    if not math.isfinite(r2) or r2 <= 0.0:
        return None
    return np.array([sol[0] + m[0], sol[1] + m[1], math.sqrt(r2)])


def _beam_cos_inc(circle: FloatArray, sin_b: FloatArray, cos_b: FloatArray) -> FloatArray:
    """Cosine of the incidence angle of each nominal beam on ``circle``; 0 if it misses.

    Computed from the beam direction, not from the measured point: an incidence (hence
    a weight or a grazing cut) depending on the point's own noise would favour points
    displaced one way and bias the radius.
    """
    lateral = np.abs(circle[0] * sin_b - circle[1] * cos_b)
    s = np.minimum(lateral / max(abs(float(circle[2])), 1e-12), 1.0)
    out: FloatArray = np.sqrt(1.0 - s * s)
    return out


# scipy's default forward-difference step (``approx_derivative``, "2-point"): √eps times
# max(1, |x|), away from zero.  The point-space circle fit's thresholds are tuned with
# exactly that Jacobian, so it is reproduced bit for bit (see :func:`_geometric_circle`).
_FD_REL_STEP = float(np.finfo(np.float64).eps) ** 0.5
# MINPACK settings of scipy's ``least_squares(method="lm")``, with which these fits are
# tuned: gtol, and 100 evaluations per parameter.
_LM_GTOL = 1e-8
_LM_EVALS_PER_PARAM = 100


def _levenberg_marquardt(
    fun: Callable[[FloatArray], FloatArray],
    jac: Callable[[FloatArray], FloatArray],
    x0: FloatArray,
    tol: float,
) -> FloatArray:
    """MINPACK's ``lmder`` from ``x0`` with ``ftol = xtol = tol`` (may return non-finite values).

    Called through :func:`scipy.optimize.leastsq` rather than ``least_squares``: the
    solver, its settings and therefore its iterates are the same, but ``least_squares``
    wraps every evaluation in bookkeeping that costs more than these 3-parameter
    problems themselves (a large share of the extraction time).
    """
    out = leastsq(
        fun,
        x0,
        Dfun=jac,
        full_output=True,  # no warning when the evaluation budget runs out
        ftol=tol,
        xtol=tol,
        gtol=_LM_GTOL,
        maxfev=_LM_EVALS_PER_PARAM * x0.size,
    )
    return np.asarray(out[0], dtype=np.float64)


def _point_circle_residuals(P: FloatArray, X: FloatArray, sig: FloatArray) -> FloatArray:
    """(k, n) ``(‖p_i − c‖ − r) / σ_i`` for each of the k circles ``(cx, cy, r)`` in ``X``."""
    dx = P[:, 0] - X[:, 0:1]
    dy = P[:, 1] - X[:, 1:2]
    out: FloatArray = (np.hypot(dx, dy) - X[:, 2:3]) / sig
    return out


def _geometric_circle(
    P: FloatArray, r: FloatArray, b: FloatArray, noise: _Noise, r_limit: float
) -> _CircleFit | None:
    """Levenberg–Marquardt on ``‖p_i − c‖ − r`` weighted by ``1 / nᵢᵀΣᵢnᵢ``.

    Decides whether the central returns of a cluster lie on a circle; its estimate is
    only the start of :func:`_refine_circle` (see there for why).  ``None`` if the
    points are collinear or the radius exceeds ``r_limit``.  The Jacobian is the forward
    difference of :data:`_FD_REL_STEP`, the three shifted evaluations done at once.
    """
    if P.shape[0] < 4:
        return None
    x = _kasa(P)
    if x is None or x[2] > r_limit:
        return None
    sin_b, cos_b = np.sin(b), np.cos(b)
    diag = np.arange(3)
    for _ in range(2):
        sig = np.sqrt(_normal_var(noise, r, _beam_cos_inc(x, sin_b, cos_b)))

        def fun(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            out: FloatArray = _point_circle_residuals(P, p[None, :], sig)[0]
            return out

        def jac(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            h = _FD_REL_STEP * np.where(p >= 0.0, 1.0, -1.0) * np.maximum(1.0, np.abs(p))
            shifted = np.tile(p, (3, 1))
            shifted[diag, diag] = p + h
            f = _point_circle_residuals(P, np.vstack((p, shifted)), sig)
            out: FloatArray = ((f[1:] - f[0]) / ((p + h) - p)[:, None]).T
            return out

        x = _levenberg_marquardt(fun, jac, x, 1e-10)
        if not np.all(np.isfinite(x)) or abs(x[2]) > r_limit:
            return None
    x[2] = abs(x[2])
    cos_inc = _beam_cos_inc(x, sin_b, cos_b)
    res = np.hypot(*(P - x[:2]).T) - x[2]
    chi2 = float(np.sum(res * res / _normal_var(noise, r, cos_inc)))
    return _CircleFit(x, chi2, cos_inc)


def _circle_system(
    b: FloatArray, x: FloatArray, noise: _Noise
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Per beam: predicted mean range, its Jacobian w.r.t. ``(cx, cy, r)``, its variance,
    the cosine of the incidence angle and the nonlinearity index of :func:`_nonlinearity`.

    Beam ``u = (cos β, sin β)``, ``u⊥ = (−sin β, cos β)``; the centre is ``a`` along and
    ``s`` across it; ``q = √(r² − s²) = r cos γ``.  Then ``ρ̂ = a − q``,
    ``∂ρ̂/∂c = u + (s/q) u⊥``, ``∂ρ̂/∂r = −r/q``, ``ρ̂' = −s ρ̂ / q`` and
    ``ρ̂'' = −a + (a² − s²)/q + s² a² / q³``.  ``q`` is floored at ``r cos 89°`` so that
    a beam that misses the current estimate still gives a finite, tiny weight.
    """
    sb, cb = np.sin(b), np.cos(b)
    a = x[0] * cb + x[1] * sb
    s = -x[0] * sb + x[1] * cb
    rad = abs(float(x[2]))
    q = np.sqrt(np.maximum(rad * rad - s * s, (rad * math.cos(math.radians(89.0))) ** 2))
    pred = a - q
    d1 = -s * pred / q
    d2 = -a + (a * a - s * s) / q + s * s * a * a / q**3
    bias, var = _range_moments(noise, d1, d2)
    k = s / q
    J = np.column_stack((cb - k * sb, sb + k * cb, -rad / q))
    return pred + bias, J, var, q / rad, _nonlinearity(noise, d2, var)


def _refine_circle(
    r: FloatArray, b: FloatArray, x0: FloatArray, noise: _Noise
) -> _CircleFit | None:
    """Levenberg–Marquardt fit of ``(cx, cy, r)`` to the measured *ranges*, from ``x0``.

    The point-space residual ``‖p_i − c‖ − r`` has the Jacobian ``[−n_i, −1]`` with
    ``n_i`` the direction from the centre to the *noisy* point: range noise moves a
    point both along the normal and (off normal incidence) along the arc, so the
    Jacobian is correlated with the residual.  On a trunk, whose radius is only ~10σ_r,
    that errors-in-variables bias is about half a σ on the radius.  Predicting the
    measured range of each nominal beam (:func:`_circle_system`) removes it, and also
    accounts for the second-order effect of the bearing noise on the mean range.
    """
    # The solver asks for the Jacobian at the point it last accepted, usually the one
    # whose residuals it just computed: keep the last system instead of recomputing it.
    last: dict[bytes, tuple[FloatArray, FloatArray]] = {}

    def system(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = p.tobytes()
        if key not in last:
            last.clear()
            last[key] = _circle_system(b, p, noise)[:2]
        return last[key]

    x = x0.copy()
    for _ in range(2):
        var = _circle_system(b, x, noise)[2]
        sig = np.sqrt(var)

        def fun(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            out: FloatArray = (r - system(p)[0]) / sig
            return out

        def jac(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            out: FloatArray = -system(p)[1] / sig[:, None]
            return out

        x = _levenberg_marquardt(fun, jac, x, 1e-12)
        if not np.all(np.isfinite(x)):
            return None
    x[2] = abs(x[2])
    mean, J, var, cos_inc, _ = _circle_system(b, x, noise)
    cov = _gauss_newton_cov(J, 1.0 / var, 1e12)
    if cov is None:
        return None
    res = r - mean
    return _CircleFit(x, float(np.sum(res * res / var)), cos_inc, cov)


def _circle_beams_usable(
    cos_inc: FloatArray, eta: FloatArray, params: ExtractionParams
) -> np.ndarray:
    """Beams below the grazing cut whose range the linearised model describes."""
    return np.asarray(
        (cos_inc >= math.cos(params.max_circle_incidence_rad))
        & (eta <= params.max_range_nonlinearity)
    )


def _circle_beams(
    r: FloatArray,
    b: FloatArray,
    span: tuple[float, float],
    noise: _Noise,
    params: ExtractionParams,
) -> tuple[np.ndarray, float]:
    """Beams to fit a circle to, and the ``r / σ_r`` that fit would have.

    Both come from a *hypothetical* circle built from the cluster's bearings alone:
    ``span`` holds the bearings of its outermost returns before trimming, and the
    tangent beams lie on average half a beam spacing beyond them.  The circle is centred
    on the mid bearing at the distance that makes those beams tangent given the median
    range ``ρ̃`` (``r = ρ̃ sin h / (1 − sin h)``, ``h`` the half span).  Beams that would
    graze it (:func:`_circle_beams_usable`) are left out, and ``σ_r`` is the one
    :func:`_refine_circle` reports, evaluated on this circle.

    Nothing here depends on the fitted radius, whose error is what the covariance has to
    describe: choosing the beams, or accepting the circle, on the fitted radius or its
    σ_r keeps the noise realisations that look most curved and biases the radius low.
    """
    none = np.zeros(b.size, dtype=bool)
    spacing = float(b[1] - b[0]) if b.size > 1 else 0.0
    half = 0.5 * (span[1] - span[0] + spacing)
    sh = math.sin(min(half, 0.5 * math.pi - 1e-3))
    rho = _median(r)
    rad = rho * sh / (1.0 - sh)
    if rad <= 0.0:
        return none, 0.0
    mid = 0.5 * (span[0] + span[1])
    c = np.array([(rho + rad) * math.cos(mid), (rho + rad) * math.sin(mid), rad])
    _, J, var, cos_inc, eta = _circle_system(b, c, noise)
    keep = _circle_beams_usable(cos_inc, eta, params)
    if np.count_nonzero(keep) < params.min_circle_points:
        return keep, 0.0
    cov = _gauss_newton_cov(J[keep], 1.0 / var[keep], 1e12)
    if cov is None:
        return keep, 0.0
    return keep, rad / math.sqrt(float(cov[2, 2]))


def _crosses_silhouette(
    x: FloatArray, cov: FloatArray | None, outside: tuple[FloatArray, FloatArray], noise: _Noise
) -> bool:
    """Whether a beam beside the cluster passes through circle ``x`` (``cov`` its
    covariance, or ``None``) well before its measured range.

    The beam must cross the circle by more than 3 σ: ``g = r − |u × c|``, the depth of
    the beam ``u`` inside the silhouette, has the variance of the fit (``cov``) and of
    the beam's own bearing error.  Testing the fitted circle itself (``g > 0``) would
    reject the fits whose radius comes out too large and keep those too small, which
    biases the radius and pulls the centre towards the laser (``docs/extraction.md``).
    """
    ranges, bearings = outside
    cb, sb = np.cos(bearings), np.sin(bearings)
    cross = cb * x[1] - sb * x[0]
    depth = abs(float(x[2])) - np.abs(cross)
    if cov is None:
        deep = depth > 0.0
    else:
        sign = np.sign(cross)
        J = np.column_stack((sign * sb, -sign * cb, np.ones_like(cb)))
        along = cb * x[0] + sb * x[1]
        var = np.einsum("ij,jk,ik->i", J, cov, J) + along * along * noise.var_b
        deep = depth > 3.0 * np.sqrt(var)
    if not deep.any():
        return False
    mean, _, var_r, _, _ = _circle_system(bearings, x, noise)
    return bool(np.any(deep & (mean < ranges - 3.0 * np.sqrt(var_r))))


def _circle_from_cluster(
    P: FloatArray,
    r: FloatArray,
    b: FloatArray,
    ids: np.ndarray,
    span: tuple[float, float],
    outside: tuple[FloatArray, FloatArray],
    noise: _Noise,
    params: ExtractionParams,
) -> ExtractedFeature | str | None:
    """A circle feature, the reason a circle was rejected, or ``None`` if not a circle.

    ``outside`` holds the ranges and bearings of the beams just beyond both ends of the
    cluster (``inf`` for no return).
    """
    keep, snr = _circle_beams(r, b, span, noise, params)
    if snr < params.min_circle_snr:
        return None
    P, r, b, ids = P[keep], r[keep], b[keep], ids[keep]
    n_pts = r.size
    geo = _geometric_circle(P, r, b, noise, 4.0 * params.circle_radius_max_m)
    if geo is None or geo.chi2 > _chi2_max(params, n_pts - 3):
        return None
    # A laser sees the near side of a trunk: the centre lies behind the points.
    if math.hypot(geo.x[0], geo.x[1]) <= float(np.mean(r)):
        return None
    fit = _refine_circle(r, b, geo.x, noise)
    # A trunk is bounded by its silhouette: the beams beside the cluster must not pass
    # through the fitted circle well before their measured range.  A short wall piece
    # or a building corner that happens to fit an arc fails this.
    if outside[0].size:
        # Without a covariance (the refinement failed) the fitted circle itself is tested.
        x, cov = (fit.x, fit.cov) if fit is not None and fit.cov is not None else (geo.x, None)
        if _crosses_silhouette(x, cov, outside, noise):
            return None
    # From here on the cluster is curved like a trunk: reject it rather than cut lines.
    if fit is None or fit.cov is None:
        return "ill_conditioned"
    if fit.chi2 > _chi2_max(params, n_pts - 3):
        return "poor_fit"
    if not params.circle_radius_min_m <= fit.x[2] <= params.circle_radius_max_m:
        return "radius_out_of_range"
    if math.sqrt(fit.cov[2, 2]) > params.max_circle_radius_rel_sigma * fit.x[2]:
        return "ill_conditioned"
    return ExtractedFeature(
        kind=FeatureKind.CIRCLE,
        params=fit.x.copy(),
        cov=fit.cov,
        true_id=_label(ids, params.label_majority),
        n_points=n_pts,
        extent=(math.nan, math.nan),
    )


# --------------------------------------------------------------------------- scan


def _label(hit_ids: np.ndarray, majority: float) -> int:
    """World id of at least ``majority`` of the points, else −1."""
    if hit_ids.size == 0:
        return -1
    # Nearly always a single id; np.unique costs as much as a line fit.
    first = int(hit_ids[0])
    if (hit_ids == first).all():
        return first if first >= 0 else -1
    ids, counts = np.unique(hit_ids, return_counts=True)
    k = int(np.argmax(counts))
    if ids[k] >= 0 and counts[k] >= majority * hit_ids.size:
        return int(ids[k])
    return -1


def _segment(scan: Scan, laser: LaserParams, params: ExtractionParams) -> list[np.ndarray]:
    """Clusters of beam indices: consecutive returns without an occlusion-size gap."""
    idx = np.flatnonzero(scan.valid())
    if idx.size == 0:
        return []
    r = scan.ranges[idx]
    b = scan.bearings[idx]
    P = np.column_stack((r * np.cos(b), r * np.sin(b)))
    gap = np.hypot(*(P[1:] - P[:-1]).T)
    tol = params.jump_abs_m + params.jump_beams * np.minimum(r[1:], r[:-1]) * (
        laser.beam_spacing_rad
    )
    breaks = (np.diff(idx) > 1) | (gap > tol)
    return np.split(idx, np.flatnonzero(breaks) + 1)


def _outside_occluded_ends(
    scan: Scan, b: FloatArray, ends: list[tuple[int, int]], margin: float
) -> np.ndarray:
    """Mask of the returns at bearings ``b`` farther than ``margin`` in bearing from
    every occluded cluster end.

    ``ends`` pairs the beam index of each outermost return of the cluster (before
    ``end_trim``) with that of the beam just beyond it; the end is occluded when that
    beam's return is nearer.
    """
    keep = np.ones(b.size, dtype=bool)
    for end, beyond in ends:
        if scan.ranges[beyond] < scan.ranges[end]:
            keep &= np.abs(b - scan.bearings[end]) > margin
    return keep


def extract_features(
    scan: Scan, laser: LaserParams, params: ExtractionParams = ExtractionParams()
) -> ExtractionResult:
    """Extract lines and circles from ``scan`` (sensor frame) with their covariances.

    ``laser`` supplies the noise model (σρ, σβ) and the beam spacing; it must be the
    laser the scan came from.  An empty scan, or one without returns, gives no
    features.  See the module docstring for the method and the rejection rules.
    """
    if not isinstance(scan, Scan):
        raise ValueError(f"scan must be a Scan, got {type(scan).__name__}")
    if not isinstance(laser, LaserParams):
        raise ValueError(f"laser must be a LaserParams, got {type(laser).__name__}")
    if not isinstance(params, ExtractionParams):
        raise ValueError(f"params must be an ExtractionParams, got {type(params).__name__}")
    if scan.bearings.size not in (0, laser.n_beams):
        raise ValueError(
            f"scan has {scan.bearings.size} beams but the laser has n_beams={laser.n_beams}"
        )
    if scan.bearings.size > 1 and np.any(np.diff(scan.bearings) <= 0.0):
        raise ValueError("scan.bearings must be strictly increasing")

    noise = _Noise(
        var_r=laser.sigma_range_m**2,
        var_b=laser.sigma_bearing_rad**2,
        floor2=params.sigma_floor_m**2,
    )
    rejected: Counter[str] = Counter()
    features: list[ExtractedFeature] = []
    min_pts = min(params.min_line_points, params.min_circle_points)
    # Round-off in the bearings must not decide whether a beam is inside the margin.
    end_margin = params.corner_margin_sigma * laser.sigma_bearing_rad * (1.0 + 1e-9)
    n_beams = scan.bearings.size
    for cl in _segment(scan, laser, params):
        # Most clusters are a few returns (far trunks, wall slivers): reject them first.
        if cl.size - 2 * params.end_trim < min_pts:
            rejected["too_few_points"] += 1
            continue
        span_b = (float(scan.bearings[cl[0]]), float(scan.bearings[cl[-1]]))
        at_fov_edge = bool(cl[0] == 0 or cl[-1] == n_beams - 1)
        ends = [(e, j) for e, j in ((cl[0], cl[0] - 1), (cl[-1], cl[-1] + 1)) if 0 <= j < n_beams]
        beside = np.array([j for _, j in ends], dtype=int)
        outside = (scan.ranges[beside], scan.bearings[beside])
        if params.end_trim:
            cl = cl[params.end_trim : cl.size - params.end_trim]
        r = scan.ranges[cl]
        b = scan.bearings[cl]
        ids = scan.hit_ids[cl]
        P = np.column_stack((r * np.cos(b), r * np.sin(b)))
        chord = float(np.hypot(*(P[-1] - P[0])))
        # A cluster cut by the edge of the field of view has no silhouette on that side:
        # its span says nothing about a radius, and an arc there cannot be checked.
        if (
            not at_fov_edge
            and cl.size >= params.min_circle_points
            and chord <= 2.2 * params.circle_radius_max_m
        ):
            circ = _circle_from_cluster(P, r, b, ids, span_b, outside, noise, params)
            if isinstance(circ, ExtractedFeature):
                features.append(circ)
                continue
            if isinstance(circ, str):
                rejected[circ] += 1
                continue
        # Cheap exits for the many small clusters (far trunks, wall slivers); no segment
        # of a cluster can be longer than the diagonal of its bounding box.
        if cl.size < params.min_line_points:
            rejected["too_few_points"] += 1
            continue
        if float(np.hypot(*np.ptp(P, axis=0))) < params.min_line_length_m:
            rejected["too_short"] += 1
            continue
        if params.occluded_end_margin:
            keep = _outside_occluded_ends(scan, b, ends, end_margin)
            if not keep.all():
                P, r, b, ids = P[keep], r[keep], b[keep], ids[keep]
        features.extend(_lines_from_cluster(P, r, b, ids, noise, laser, params, rejected))
    return ExtractionResult(features=tuple(features), rejected=dict(sorted(rejected.items())))
