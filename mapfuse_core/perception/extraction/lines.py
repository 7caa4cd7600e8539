"""Lines: split-and-merge, total-least-squares fit, range-space refinement.

Each segment is fitted in normal form ``(ρ, α)`` by weighted total least squares on
the points (:func:`_tls_line`, used for the split-and-merge decisions), then by
Gauss–Newton on the measured ranges (:func:`_refine_line`), whose normal matrix gives
the covariance.  The SPmap frame is placed at the segment midpoint
(:func:`mapfuse_core.geometry.features.line_from_normal`).  Why the final fit works on the
ranges, and which returns are left out, is explained in the package docstring of
:mod:`mapfuse_core.perception.extraction`.
"""

from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass

import numpy as np

from mapfuse_core.geometry.features import FeatureKind, line_from_normal
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.perception.extraction.labels import _label
from mapfuse_core.perception.extraction.noise import (
    _chi2_max,
    _Noise,
    _normal_var,
    _range_moments,
    line_model_cov,
)
from mapfuse_core.perception.extraction.params import ExtractedFeature, ExtractionParams
from mapfuse_core.sensor import LaserParams


def _min_normal(S: FloatArray) -> FloatArray:
    """Unit eigenvector of the smaller eigenvalue of a symmetric 2×2 scatter matrix."""
    # The major axis of [[a, b], [b, c]] is at ½ atan2(2b, a − c); the normal is ⊥ to it.
    phi = 0.5 * math.atan2(2.0 * S[0, 1], S[0, 0] - S[1, 1]) + 0.5 * math.pi
    return np.array([math.cos(phi), math.sin(phi)])


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
    mean and variance of :func:`~mapfuse_core.perception.extraction.noise._range_moments`
    (``ρ̂' = ρ̂ tan γ``, ``ρ̂'' = ρ̂ (2 tan²γ + 1)``) and the Jacobian
    ``(1 / cos γ_i, −ρ̂_i tan γ_i)``.  The point-space residual ``p_i·n − ρ`` has the
    Jacobian ``p_i·t``, which carries the noise of ``p_i`` itself (range noise moves a
    point along and across the line at once): an errors-in-variables bias that this
    formulation does not have.
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
    cov = J @ C @ J.T + line_model_cov(line, params.line_model_sigma_m, params.line_model_sigma_rad)
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
