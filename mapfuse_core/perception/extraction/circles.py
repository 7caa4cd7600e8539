"""Circles: candidate beams, Kåsa and geometric fits, range-space fit, silhouette test.

A cluster becomes a circle candidate from its size alone (:func:`_silhouette_candidates`).
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
from scipy.special import log_ndtr

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle, wrap_scalar
from mapfuse_core.perception.extraction.labels import _label
from mapfuse_core.perception.extraction.noise import (
    _chi2_max,
    _edge_moments,
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


@dataclass(frozen=True)
class _Edges:
    """Silhouette edges of a cluster: where the beams stop hitting the trunk."""

    tau: FloatArray
    """(m,) bearing of each edge read from the beams, half a spacing beyond the cluster's
    outermost return (rad); m is 0, 1 or 2."""
    side: FloatArray
    """(m,) +1 for the counter-clockwise (upper) edge, −1 for the lower one."""
    bias: float
    """Mean of an edge reading minus the true tangent bearing, outwards positive (rad;
    :func:`~mapfuse_core.perception.extraction.noise._edge_moments`)."""
    var: float
    """Variance of an edge reading (rad²)."""
    v_min: float
    """The cluster is a circle candidate only if ``Σ side · tau`` is at least this
    (rad): the detection rule as a bound on the readings (:func:`_silhouette_edges`)."""


_NO_EDGES = _Edges(np.zeros(0), np.zeros(0), 0.0, 1.0, -math.inf)


def _silhouette_edges(
    end_ranges: tuple[float, float],
    span: tuple[float, float],
    beyond_ranges: FloatArray,
    spacing: float,
    min_size: int,
    noise: _Noise,
) -> _Edges:
    """The silhouette edges of a cluster whose outermost returns have ranges
    ``end_ranges`` at bearings ``span`` (lower end first), with ``beyond_ranges`` the
    returns just beyond them (``inf`` for none).

    An end is a silhouette edge when the beam beyond it returns from farther away, or
    not at all: that beam passed the trunk.  A nearer return beyond an end is an
    occluder, and the trunk's edge behind it is unseen.

    A cluster of ``n`` returns spans ``Σ_ends side · (β_end + side Δβ/2) = n Δβ``; it
    is a circle candidate only from ``min_size`` returns on (:func:`_circle_from_cluster`),
    which bounds the silhouette edges' ``Σ side · tau`` from below given the bearings of
    the occluded ends (:attr:`_Edges.v_min`, with a whole number of returns read as
    ``n Δβ ≥ (min_size − ½) Δβ``).
    """
    side_all = np.array([-1.0, 1.0])
    tau_all = np.asarray(span, dtype=np.float64) + side_all * 0.5 * spacing
    keep = np.asarray(beyond_ranges, dtype=np.float64) > np.asarray(end_ranges)
    occluded = float(np.sum(side_all[~keep] * tau_all[~keep]))
    mean, var = _edge_moments(math.sqrt(noise.var_b) / spacing)
    return _Edges(
        tau=tau_all[keep],
        side=side_all[keep],
        bias=mean * spacing,
        var=var * spacing * spacing,
        v_min=(min_size - 0.5) * spacing - occluded,
    )


def _edge_rows(
    x: FloatArray, edges: _Edges
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The edge readings as the range-space fit uses them: readings, their means at
    circle ``x``, the means' Jacobian w.r.t. ``(cx, cy, r)`` and their variances.

    The tangent bearings from the sensor are ``φ ± h``, ``h = asin(r / D)`` (centre at
    bearing ``φ`` and distance ``D``); a reading is off by :attr:`_Edges.bias`
    outwards on average.  The first row is ``v = Σ side · τ̂`` (the angular width, or
    one edge's bearing); with two edges the second is their mean ``(τ̂₊ + τ̂₋)/2``, the
    centre's bearing, independent of ``v``.  ``D² − r²`` is floored so that a circle
    reaching the sensor stays finite.
    """
    cx, cy, rad = float(x[0]), float(x[1]), float(x[2])
    d2 = cx * cx + cy * cy
    rad_abs = abs(rad)
    q = math.sqrt(max(d2 - rad_abs * rad_abs, 1e-6 * d2))
    phi = math.atan2(cy, cx)
    d_phi = np.array([-cy / d2, cx / d2, 0.0])
    # h = asin(r/D): ∂h/∂c = −r c / (D² q), ∂h/∂r = 1/q (with the sign of r).
    d_half = np.array(
        [-rad_abs * cx / (d2 * q), -rad_abs * cy / (d2 * q), math.copysign(1.0 / q, rad)]
    )
    k = edges.tau.size
    s_sum = float(edges.side.sum())
    meas = [float(edges.side @ edges.tau)]
    mean = [s_sum * phi + k * (math.atan2(rad_abs, q) + edges.bias)]
    J = [s_sum * d_phi + k * d_half]
    var = [k * edges.var]
    if k == 2:
        meas.append(float(edges.tau.mean()))
        mean.append(phi)
        J.append(d_phi)
        var.append(0.5 * edges.var)
    return np.array(meas), np.array(mean), np.vstack(J), np.array(var)


def _detection_correction(
    x: FloatArray, cov: FloatArray, edges: _Edges
) -> tuple[FloatArray, FloatArray]:
    """The fit ``x`` (covariance ``cov``) corrected, to first order, for the detection
    rule, and the covariance of the corrected fit.

    A cluster is a circle candidate only from a certain size on, i.e. only when the
    edges' ``v`` reaches :attr:`_Edges.v_min`.  Near that size the clusters whose edges
    read wide are the ones seen: taken as normal with mean ``μ`` and standard deviation
    ``σ``, a detected ``v`` exceeds ``μ`` by ``σ λ`` on average and varies by
    ``σ² (1 − t)``, with ``α = (v_min − μ) / σ``, ``λ`` the inverse Mills ratio at ``α``
    and ``t = λ (λ − α)``.  The fit passes the excess on through the gain of its ``v``
    row, ``k = C Jᵥᵀ / σ²``, and the excess evaluated at the fit is subtracted.  The
    corrected fit then follows ``v`` with the gain ``k (1 + g t)`` (``g = Jᵥ k``, the
    part of ``v`` the fit's ``μ`` takes up) on the narrower spread of a detected ``v``,
    so its covariance is ``C + k kᵀ σ² ((1 + g t)² (1 − t) − 1)``.

    Evaluated at the fit, the excess removes about half to two thirds of the bias where
    half the clusters are detected (``docs/results/extraction.md``).  Solving instead for the
    circle whose truncated mean matches ``v`` overshoots: a reading at the threshold
    says little about how far below it the circle is.
    """
    if edges.tau.size == 0 or not math.isfinite(edges.v_min):
        return x, cov
    meas, mean, J, var = _edge_rows(x, edges)
    sd = math.sqrt(var[0])
    # One edge's bearing and the bound are compared on the same branch of the angle.
    alpha = (edges.v_min - meas[0] + wrap_scalar(meas[0] - mean[0])) / sd
    lam = math.exp(_log_mills(alpha))
    t = min(lam * (lam - alpha), 1.0)
    gain = cov @ J[0] / var[0]
    g = float(J[0] @ gain)
    factor = (1.0 + g * t) ** 2 * (1.0 - t) - 1.0
    out_cov = cov + np.outer(gain, gain) * (var[0] * factor)
    return x - gain * (sd * lam), 0.5 * (out_cov + out_cov.T)


def _log_mills(alpha: float) -> float:
    """``log(φ(α) / (1 − Φ(α)))``, the log of the inverse Mills ratio, without overflow."""
    return float(-0.5 * alpha * alpha - 0.5 * math.log(2.0 * math.pi) - log_ndtr(-alpha))


def _silhouette_candidates(
    rho: float, spacing: float, n: np.ndarray, noise: _Noise, params: ExtractionParams
) -> tuple[FloatArray, np.ndarray]:
    """For a cluster of each size in ``n`` with median range ``rho``: the ``r / σ_r`` a
    fit to the ranges of its usable beams would have, and which of its trimmed beams
    (``(len(n), max n − 2·end_trim)``, centred) are usable.

    Both come from a *hypothetical* circle built from the cluster's bearings alone: the
    tangent beams lie on average half a beam spacing beyond its outermost returns, so
    the silhouette's half angle is ``h = n Δβ / 2``; the circle is centred on the mid
    bearing at the distance that makes those beams tangent given ``rho``
    (``r = ρ̃ sin h / (1 − sin h)``).  Beams that would graze it
    (:func:`_circle_beams_usable`) are left out, ``σ_r`` is evaluated on this circle
    (:func:`_circle_system`'s arithmetic for all the sizes at once), and a ratio is 0
    when fewer than ``min_circle_points`` beams are usable.

    Nothing here depends on the fitted radius, whose error is what the covariance has to
    describe: choosing the beams, or accepting the circle, on the fitted radius or its
    σ_r keeps the noise realisations that look most curved and biases the radius low.
    The size is itself a reading of the silhouette, which the fit uses; the fit allows
    for the choice (:func:`_detection_correction`).
    """
    n_fit = n - 2 * params.end_trim
    k = np.arange(int(n_fit.max()))[None, :]
    valid = k < n_fit[:, None]
    beta = (k - 0.5 * (n_fit[:, None] - 1)) * spacing
    sh = np.sin(np.minimum(0.5 * n * spacing, 0.5 * math.pi - 1e-3))
    rad = (rho * sh / (1.0 - sh))[:, None]
    dist = rho + rad
    sb, cb = np.sin(beta), np.cos(beta)
    a = dist * cb
    s = -dist * sb
    q = np.sqrt(np.maximum(rad * rad - s * s, (rad * math.cos(math.radians(89.0))) ** 2))
    pred = a - q
    d2 = -a + (a * a - s * s) / q + s * s * a * a / q**3
    var = _range_moments(noise, -s * pred / q, d2)[1]
    keep = valid & _circle_beams_usable(q / rad, _nonlinearity(noise, d2, var), params)
    ks = s / q
    J = np.stack((cb - ks * sb, sb + ks * cb, -rad / q * np.ones_like(cb)), axis=-1)
    N = np.einsum("nk,nki,nkj->nij", np.where(keep, 1.0 / var, 0.0), J, J)
    ev = np.linalg.eigvalsh(N)
    ok = (np.count_nonzero(keep, axis=1) >= params.min_circle_points) & (ev[:, 0] > 0.0)
    ok &= ev[:, -1] <= 1e12 * ev[:, 0]
    snr = np.zeros(n.size)
    if ok.any():
        snr[ok] = rad[ok, 0] / np.sqrt(np.linalg.inv(N[ok])[:, 2, 2])
    return snr, keep


def _central(b: FloatArray, mid: float, k: int) -> np.ndarray:
    """Mask of the ``k`` beams of ``b`` nearest to bearing ``mid`` (ties to the lower)."""
    order = np.argsort(np.abs(b - mid), kind="stable")
    out = np.zeros(b.size, dtype=bool)
    out[order[:k]] = True
    return out


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
    r: FloatArray, b: FloatArray, x0: FloatArray, noise: _Noise, edges: _Edges = _NO_EDGES
) -> _CircleFit | None:
    """Levenberg–Marquardt fit of ``(cx, cy, r)`` to the measured *ranges* and the
    silhouette ``edges``, from ``x0``.

    The point-space residual ``‖p_i − c‖ − r`` has the Jacobian ``[−n_i, −1]`` with
    ``n_i`` the direction from the centre to the *noisy* point: range noise moves a
    point both along the normal and (off normal incidence) along the arc, so the
    Jacobian is correlated with the residual.  On a trunk, whose radius is known only to
    about a tenth, that errors-in-variables bias is a large fraction of σ on the radius
    (``docs/results/extraction.md``).  Predicting the
    measured range of each nominal beam (:func:`_circle_system`) removes it, and also
    accounts for the second-order effect of the bearing noise on the mean range.

    The ranges alone fix the radius of a short arc only through its curvature, to a
    fifth or so: the fit is then far from linear (it errs outwards by a fifth of its σ),
    and the information the arc holds grows as the radius shrinks, so a covariance
    taken at the fitted circle is smaller exactly when the radius came out too small
    (``docs/results/extraction.md``).  The silhouette edges (:func:`_edge_rows`) fix the
    angular width ``2 asin(r/D)`` to a fraction of a beam spacing whatever the radius:
    with them the radius is known several times better, the fit is close to linear and
    its covariance does not follow its error.  The fit is finally corrected for the
    detection rule (:func:`_detection_correction`).
    """
    # The solver asks for the Jacobian at the point it last accepted, usually the one
    # whose residuals it just computed: keep the last system instead of recomputing it.
    last: dict[bytes, tuple[FloatArray, FloatArray]] = {}
    n = r.size
    has_edges = edges.tau.size > 0

    def system(p: FloatArray) -> tuple[FloatArray, FloatArray]:
        key = p.tobytes()
        if key not in last:
            last.clear()
            mean, J = _circle_system(b, p, noise)[:2]
            if has_edges:
                _, e_mean, e_J, _ = _edge_rows(p, edges)
                mean, J = np.concatenate((mean, e_mean)), np.vstack((J, e_J))
            last[key] = (mean, J)
        return last[key]

    meas = np.concatenate((r, _edge_rows(x0, edges)[0])) if has_edges else r

    def variances(p: FloatArray) -> FloatArray:
        var = _circle_system(b, p, noise)[2]
        return np.concatenate((var, _edge_rows(p, edges)[3])) if has_edges else var

    def residual(p: FloatArray, sig: FloatArray) -> FloatArray:
        res = meas - system(p)[0]
        res[n:] = wrap_angle(res[n:])  # edge readings are angles
        out: FloatArray = res / sig
        return out

    x = x0.copy()
    for _ in range(2):
        sig = np.sqrt(variances(x))

        def fun(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            return residual(p, sig)

        def jac(p: FloatArray, sig: FloatArray = sig) -> FloatArray:
            out: FloatArray = -system(p)[1] / sig[:, None]
            return out

        x = _levenberg_marquardt(fun, jac, x, 1e-12)
        if not np.all(np.isfinite(x)):
            return None
    x[2] = abs(x[2])
    var = variances(x)
    cov = _gauss_newton_cov(system(x)[1], 1.0 / var, 1e12)
    if cov is None:
        return None
    z = residual(x, np.sqrt(var))
    cos_inc = _circle_system(b, x, noise)[3]
    x, cov = _detection_correction(x, cov, edges)
    x[2] = abs(x[2])
    return _CircleFit(x, float(z @ z), cos_inc, cov)


def _circle_beams_usable(
    cos_inc: FloatArray, eta: FloatArray, params: ExtractionParams
) -> np.ndarray:
    """Beams below the grazing cut whose range the linearised model describes."""
    return np.asarray(
        (cos_inc >= math.cos(params.max_circle_incidence_rad))
        & (eta <= params.max_range_nonlinearity)
    )


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


def _candidate_beams(
    r: FloatArray, b: FloatArray, span: tuple[float, float], noise: _Noise, params: ExtractionParams
) -> tuple[np.ndarray, np.ndarray, int] | None:
    """Whether a cluster (trimmed ranges ``r`` at bearings ``b``, outermost returns at
    ``span``) is a circle candidate: if so its usable beams, the central beams whose
    ranges the fit uses, and the smallest size a candidate has at its range.

    Every cluster at least as large as the smallest that qualifies
    (:func:`_silhouette_candidates`) is a candidate: ``r / σ_r`` is not monotone in
    the size (each time the grazing cut drops the outermost pair of beams it falls
    back), and the fit needs the detection rule to be a bound on the silhouette's
    width, not a set of gaps in it (:attr:`_Edges.v_min`).

    The ranges fitted are those of the central beams that the smallest candidate at this
    range has usable, whatever the cluster's own size: with all of its usable beams the
    fit's gain on the silhouette's width would depend on the width read (a wider reading
    brings in more beams near the edges, whose ranges pull the radius back), and its
    radius came out −0.07 σ low on trunks far from the detection limit.
    """
    spacing = float(b[1] - b[0])
    trim = 2 * params.end_trim
    sizes = np.arange(trim + params.min_circle_points, r.size + trim + 1)
    if sizes.size == 0:
        return None
    snr, usable = _silhouette_candidates(_median(r), spacing, sizes, noise, params)
    first = np.flatnonzero(snr >= params.min_circle_snr)
    keep = usable[-1, : r.size]
    if first.size == 0 or np.count_nonzero(keep) < params.min_circle_points:
        return None
    n_central = int(np.count_nonzero(usable[first[0]]))
    central = _central(b, 0.5 * (span[0] + span[1]), n_central) & keep
    return keep, central, int(sizes[first[0]])


def _circle_from_cluster(
    P: FloatArray,
    r: FloatArray,
    b: FloatArray,
    ids: np.ndarray,
    span: tuple[float, float],
    outside: tuple[FloatArray, FloatArray],
    end_ranges: tuple[float, float],
    noise: _Noise,
    params: ExtractionParams,
) -> ExtractedFeature | str | None:
    """A circle feature, the reason a circle was rejected, or ``None`` if not a circle.

    ``span`` holds the bearings and ``end_ranges`` the ranges of the cluster's outermost
    returns (before trimming), ``outside`` the ranges and bearings of the beams just
    beyond both ends (``inf`` for no return).
    """
    chosen = _candidate_beams(r, b, span, noise, params)
    if chosen is None:
        return None
    keep, central, min_size = chosen
    edges = _silhouette_edges(end_ranges, span, outside[0], float(b[1] - b[0]), min_size, noise)
    P, r, b, ids = P[keep], r[keep], b[keep], ids[keep]
    n_pts = r.size
    geo = _geometric_circle(P, r, b, noise, 4.0 * params.circle_radius_max_m)
    if geo is None or geo.chi2 > _chi2_max(params, n_pts - 3):
        return None
    # A laser sees the near side of a trunk: the centre lies behind the points.
    if math.hypot(geo.x[0], geo.x[1]) <= float(np.mean(r)):
        return None
    central = central[keep]
    n_pts = int(np.count_nonzero(central))
    fit = _refine_circle(r[central], b[central], geo.x, noise, edges)
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
    if fit.chi2 > _chi2_max(params, n_pts + edges.tau.size - 3):
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
