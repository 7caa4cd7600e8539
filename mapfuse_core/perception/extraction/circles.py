"""Circles: candidate beams, Kåsa and geometric fits, range-space fit, silhouette test.

A cluster becomes a circle candidate from its bearings alone (:func:`_circle_beams`).
The decision uses an algebraic start (:func:`_kasa`) and a point-space
Levenberg–Marquardt fit (:func:`_geometric_circle`); the estimate and its covariance
come from Levenberg–Marquardt on the measured ranges (:func:`_refine_circle`).  A
circle that a beam beside the cluster crosses is rejected
(:func:`_crosses_silhouette`).  Why each rule is needed is explained in the package
docstring of :mod:`mapfuse_core.perception.extraction`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.optimize import leastsq

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.perception.extraction.labels import _label
from mapfuse_core.perception.extraction.noise import (
    _chi2_max,
    _Noise,
    _nonlinearity,
    _normal_var,
    _range_moments,
)
from mapfuse_core.perception.extraction.params import ExtractedFeature, ExtractionParams


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
    wraps every call in bookkeeping that is a sizeable part of the cost of these
    3-parameter problems, and these calls are a large share of the extraction time
    (``docs/results/extraction.md``).
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
    the cosine of the incidence angle and the nonlinearity index of
    :func:`~mapfuse_core.perception.extraction.noise._nonlinearity`.

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
    Jacobian is correlated with the residual.  On a trunk, whose radius is known only to
    about a tenth, that errors-in-variables bias is a large fraction of σ on the radius
    (``docs/results/extraction.md``).  Predicting the
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
    biases the radius and pulls the centre towards the laser (``docs/results/extraction.md``).
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
