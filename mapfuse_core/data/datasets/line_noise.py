"""The line model-error terms of a log with a reference trajectory, from its own scans.

A real wall is not the straight line the extractor fits (bowed plaster, skirting
boards, door frames, furniture against it), and the part of that departure all
returns of one segment share is not averaged away by more returns: it is a model
error, added to every line's covariance as a σ on the normal's distance ``ρ`` and one
on its direction ``α`` (:func:`~mapfuse_core.perception.extraction.noise.line_model_cov`).
It also repeats from one scan to the next while the sensor sees the same piece of wall
from nearly the same place, so an estimator that takes consecutive observations as
independent counts the same error several times.

:func:`estimate_line_model_error` measures both on the log itself.  It builds the
log's floor plan (each wall the mean of the observations clustered on it, with the
standard error of that mean and no survey σ), and compares every observation with its
wall at the reference pose as the estimators compare an observation with its landmark
(:func:`~mapfuse_core.models.dispatch.observe`: the lateral offset of the
observation's reference point from the wall's line, and the angle), against the
observation's own covariance plus the wall's.  Then, per degree of freedom:

1. the σ that makes the mean whitened squared residual 1;
2. with it, the integrated autocorrelation time ``τ = 1 + 2 Σ ρ_L`` of the whitened
   residuals of one wall ``L`` scans apart (pooled over the walls, summed while the
   correlation stays above :data:`MIN_CORRELATION`);
3. the σ that makes that mean ``1/τ``: each observation then carries ``1/τ`` of the
   information it would carry alone, which is what a run of ``τ`` correlated
   observations is worth about what they share;
4. steps 2–3 again until ``τ`` settles (the terms reweight the observations, which
   moves ``τ`` a little): the ``τ`` reported is that of the residuals whitened with
   the terms reported.

Steps 1 and 3 answer two questions.  Step 1's terms say how far one observation
strays from its wall, which is what an association gate tests
(:attr:`LineModelError.gate_sigma_m`, the log's
:attr:`~mapfuse_core.measlog.MeasurementLog.feat_gate_cov`); step 3's say how much it
tells about the wall beside its neighbours in time, which is what an update weighs.
Gating with step 3's would admit pairings up to ``√τ`` times farther than one
observation strays.

The angle's σ is solved first: the lateral offset depends on both terms (the angle's
through the distance from the foot of the observed line's normal to its reference
point).  The tail of the residuals is heavy (mixed-up walls, furniture); the mean
counts it, as a run's NEES does.  Measured on the seven CARMEN logs in
``docs/results/carmen.md``.

With ``shape="length"`` the σ on ``ρ`` depends on the segment's length ``L``:
``σ_ρ² = σ_m² + (σ_1 / L)²``.  Pieces of wall a metre or less long (door frames,
skirting, furniture beside a wall) stray from the wall's line several times farther
than segments of several metres, which one σ for every line cannot describe
(``docs/results/carmen.md``).  The split between the two parts is the Gaussian
maximum-likelihood one for the lateral residuals (with step 1's angle term), the
``1/L`` part kept only where the residuals give evidence for it
(:data:`_SHAPE_EVIDENCE`); steps 1–4 then scale both parts together.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Literal, get_args

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.stats import chi2 as chi2_dist

from mapfuse_core.data.datasets.common import check_choice
from mapfuse_core.data.datasets.floorplan import (
    FloorPlan,
    FloorPlanParams,
    build_floor_plan,
)
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.measlog.log import IntArray
from mapfuse_core.models import line_observation_cov, observe
from mapfuse_core.perception.extraction.noise import line_model_cov

__all__ = [
    "MIN_CORRELATION",
    "MIN_LENGTH_M",
    "MIN_OBSERVATIONS",
    "LineModelError",
    "LineModelShape",
    "LineTerms",
    "estimate_line_model_error",
    "with_line_model_error",
]

MIN_OBSERVATIONS = 50
"""Fewest line observations on plan walls from which the terms are estimated."""

MIN_CORRELATION = 0.05
"""The autocorrelation sum stops at the first lag whose correlation is at most this
(noise at the pooled sample sizes of a log, a few hundred pairs per lag)."""

_MAX_LAG = 10
"""Longest lag (scans) summed: the correlation of the seven logs is gone by lag 5."""

MIN_LENGTH_M = 0.2
"""Length (m) a shorter segment takes in the ``1/L²`` part of the σ on ``ρ``: keeps it
finite for a segment of a few returns (the indoor profile's shortest line is 0.4 m)."""

LineModelShape = Literal["constant", "length"]
"""How the σ on ``ρ`` varies from line to line: ``"constant"`` the same for every
line, ``"length"`` a constant part plus one falling as ``1/L`` (module docstring)."""

_SHARE_GRID = 101
"""Points on [0, 1] at which the ``1/L²`` part's share of the variance on ``ρ`` is
tried (steps of 0.01)."""

_LOG_VAR_MIN, _LOG_VAR_MAX = math.log(1e-14), math.log(1e2)
"""Bounds of the log-variance (m²) on ``ρ`` of a segment one metre long searched at each
share: σ from 0.1 µm to 10 m, far beyond any wall."""

_SHAPE_EVIDENCE = float(chi2_dist.ppf(0.95, 1))
"""χ²₁ 95 % quantile: the ``1/L`` part is kept only if it lowers ``−2 log L`` of the
lateral residuals by more than this, times their autocorrelation time (``τ``
consecutive residuals carry about one residual's evidence)."""

_MAX_ROUNDS = 10
"""Most rounds of the τ fixed point (three suffice on the seven logs)."""

_TAU_TOL = 0.01
"""Relative change of τ below which the fixed point has converged."""

_NEGLIGIBLE_SURVEY = 1e-9
"""The plan's survey σ while estimating (m and rad): the residuals are compared with
the merge's own standard error, not with a stated survey tolerance."""


@dataclass(frozen=True)
class LineTerms:
    """Line model-error terms as a line's covariance takes them
    (:func:`~mapfuse_core.perception.extraction.noise.line_model_cov`)."""

    sigma_m: float
    """σ (m) on every line's ``ρ``."""
    sigma_rad: float
    """σ (rad) on every line's ``α``."""
    sigma_m_metre: float = 0.0
    """σ (m) on ``ρ`` of a segment one metre long from the part that falls as
    ``1/L``: a segment ``L`` long takes ``σ_ρ² = sigma_m² + (sigma_m_metre / L)²``
    (``L`` at least :data:`MIN_LENGTH_M`)."""

    def __post_init__(self) -> None:
        for name in ("sigma_m", "sigma_rad", "sigma_m_metre"):
            _check_sigma(name, getattr(self, name))

    @classmethod
    def from_split(cls, var_m: float, var_rad: float, share: float) -> LineTerms:
        """The terms of a variance ``var_m`` on ``ρ`` of a segment one metre long,
        ``share`` of it in the part falling as ``1/L``, and ``var_rad`` on ``α``."""
        return cls(math.sqrt(var_m * (1.0 - share)), math.sqrt(var_rad), math.sqrt(var_m * share))

    def sigma_rho(self, length: float) -> float:
        """σ (m) on ``ρ`` of a segment ``length`` long."""
        if self.sigma_m_metre == 0.0:
            return self.sigma_m
        return math.hypot(self.sigma_m, self.sigma_m_metre / float(_floored(length)))

    def cov(self, line: FloatArray, length: float) -> FloatArray:
        """(3, 3) covariance the terms add to ``line``, a segment ``length`` long."""
        return line_model_cov(line, self.sigma_rho(length), self.sigma_rad)


@dataclass(frozen=True)
class LineModelError:
    """Line model-error terms estimated on one log (:func:`estimate_line_model_error`)."""

    sigma_m: float
    """σ (m) on every line's ``ρ`` (``ExtractionParams.line_model_sigma_m``)."""
    sigma_rad: float
    """σ (rad) on every line's ``α`` (``ExtractionParams.line_model_sigma_rad``)."""
    iact: tuple[float, float]
    """Integrated autocorrelation time ``τ`` (scans) of the whitened (lateral, angle)
    residuals of one wall: how many consecutive observations share one error."""
    observations: int
    """Line observations on a plan wall the estimate rests on."""
    nees_without: tuple[float, float]
    """Mean whitened squared residual (lateral, angle) without the terms."""
    gate_sigma_m: float
    """σ (m) on ``ρ`` that whitens each observation to 1 (step 1): the spread of one
    observation's error taken alone, which compatibility tests use
    (:attr:`~mapfuse_core.measlog.MeasurementLog.feat_gate_cov`)."""
    gate_sigma_rad: float
    """σ (rad) on ``α`` of the same step."""
    correlated: bool = True
    """Whether the terms count the correlation of consecutive scans (whitened
    residuals at ``1/τ``) or whiten each observation to 1 (then equal to the gate's)."""
    sigma_m_metre: float = 0.0
    """σ (m) on ``ρ`` of a segment one metre long from the part that falls as ``1/L``
    (:attr:`LineTerms.sigma_m_metre`); 0 with ``shape="constant"``."""
    gate_sigma_m_metre: float = 0.0
    """The same part of step 1's σ on ``ρ``."""
    shape: LineModelShape = "constant"
    """The shape asked for (:func:`estimate_line_model_error`); with ``"length"`` the
    ``1/L`` part is 0 where the residuals give too little evidence for it."""

    @property
    def terms(self) -> LineTerms:
        """The terms the updates weigh each observation with."""
        return LineTerms(self.sigma_m, self.sigma_rad, self.sigma_m_metre)

    @property
    def gate_terms(self) -> LineTerms:
        """Step 1's terms: each observation's error alone."""
        return LineTerms(self.gate_sigma_m, self.gate_sigma_rad, self.gate_sigma_m_metre)

    def summary(self, gated: bool = False) -> str:
        """One line for a log's metadata; ``gated``: the log's gates take
        :attr:`gate_terms`."""
        how = "correlated" if self.correlated else "independent"
        how += ", length shape" if self.shape == "length" else ""
        gate = f"; gates {_terms_text(self.gate_terms)}" if gated else ""
        return (
            f"estimated from the log ({how}): {_terms_text(self.terms)}{gate} "
            f"(autocorrelation time "
            f"{self.iact[0]:.1f} / {self.iact[1]:.1f} scans, "
            f"{self.observations} observations on plan walls)"
        )


@dataclass(frozen=True)
class _Residuals:
    """Every observation against its wall: the residuals, the diagonal of their
    covariance without the terms, and how each term enters it."""

    wall: np.ndarray
    """(N,) wall of each observation."""
    step: np.ndarray
    """(N,) its scan."""
    r: FloatArray
    """(N, 2) (lateral, angle) residual."""
    var: FloatArray
    """(N, 2) its variance without the terms (observation's and wall's)."""
    gain: FloatArray
    """(N, 2, 2) ``[d, k]``: variance added to dof ``d`` by a unit variance of term
    ``k`` (``ρ``, ``α``)."""
    inv_length2: FloatArray
    """(N,) ``1/L²`` of each observed segment (``L`` at least :data:`MIN_LENGTH_M`)."""

    def variance(self, var_m: float, var_rad: float, share: float = 0.0) -> FloatArray:
        """(N, 2) variance of each residual with the terms: ``var_m`` on ``ρ`` of a
        segment one metre long (``share`` of it falling as ``1/L²``), ``var_rad`` on
        ``α``."""
        terms = np.empty((self.r.shape[0], 2, 1))
        terms[:, 0, 0] = var_m * self.rho_weight(share)
        terms[:, 1, 0] = var_rad
        out: FloatArray = self.var + (self.gain @ terms)[:, :, 0]
        return out

    def rho_weight(self, share: float) -> FloatArray:
        """(N,) each observation's variance on ``ρ`` per unit variance of a segment one
        metre long, ``share`` of it in the ``1/L²`` part."""
        out: FloatArray = (1.0 - share) + share * self.inv_length2
        return out

    def whitened(self, var_m: float, var_rad: float, share: float = 0.0) -> FloatArray:
        """(N, 2) residuals over their standard deviation with the terms
        (:meth:`variance`)."""
        out: FloatArray = self.r / np.sqrt(self.variance(var_m, var_rad, share))
        return out


def _residuals(log: MeasurementLog, plan: FloorPlan) -> _Residuals:
    """Every observation on a plan wall against that wall at the reference pose, as the
    estimators compare a line observation with its landmark
    (:func:`~mapfuse_core.models.dispatch.observe`): the lateral offset of the
    observation's reference point from the wall's line, and the angle."""
    assert log.true_poses is not None
    idx = np.flatnonzero(plan.obs_wall >= 0)
    r = np.empty((idx.size, 2))
    var = np.empty((idx.size, 2))
    gain = np.empty((idx.size, 2, 2))
    walls = plan.walls
    for n, i in enumerate(idx.tolist()):
        z, w = log.feat_params[i], int(plan.obs_wall[i])
        pose, wall = log.true_poses[log.feat_step[i]], walls.params[w]
        r[n], _, Jw = observe(FeatureKind.LINE, z, pose, wall)
        S = line_observation_cov(pose, wall, z, log.feat_cov[i]) + Jw @ walls.covs[w] @ Jw.T
        var[n] = np.diag(S)
        for k, unit in enumerate(((1.0, 0.0), (0.0, 1.0))):
            added = line_observation_cov(pose, wall, z, line_model_cov(z, *unit))
            gain[n, :, k] = np.diag(added)
    length = _floored(log.feat_extent[idx, 1] - log.feat_extent[idx, 0])
    return _Residuals(plan.obs_wall[idx], log.feat_step[idx], r, var, gain, 1.0 / length**2)


def _floored(length: FloatArray | float) -> FloatArray:
    """Segment lengths as the ``1/L`` part takes them: at least :data:`MIN_LENGTH_M`."""
    out: FloatArray = np.maximum(length, MIN_LENGTH_M)
    return out


def _solve(f: Callable[[float], float], target: float) -> float:
    """Smallest ``v ≥ 0`` with ``f(v) ≤ target`` for a decreasing ``f`` (bisection)."""
    if not math.isfinite(f(0.0)):
        raise ValueError("the line residuals' whitened mean square is not finite")
    if f(0.0) <= target:
        return 0.0
    hi = 1e-4
    while f(hi) > target:
        hi *= 4.0
        if hi > 1e6:
            raise ValueError("no finite line model error whitens the residuals")
    lo = 0.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        if f(mid) > target:
            lo = mid
        else:
            hi = mid
    return hi


def _variances(
    res: _Residuals, target: tuple[float, float], share: float = 0.0
) -> tuple[float, float]:
    """(σ_m², σ_rad²) bringing the mean whitened squared residuals to ``target``: the
    angle's first, since it alone moves the angle residual.  ``σ_m²`` is the variance
    on ``ρ`` of a segment one metre long, ``share`` of it falling as ``1/L²``."""

    def mean_nees(d: int, var_m: float, var_rad: float) -> float:
        return float(np.mean(res.whitened(var_m, var_rad, share)[:, d] ** 2))

    var_rad = _solve(lambda v: mean_nees(1, 0.0, v), target[1])
    var_m = _solve(lambda v: mean_nees(0, v, var_rad), target[0])
    return var_m, var_rad


def _length_share(res: _Residuals, var_rad: float, tau: float) -> float:
    """The share of the ``1/L²`` part in the variance on ``ρ`` that maximises the
    Gaussian likelihood of the lateral residuals (``var_rad`` on ``α``): for each share
    on a grid over [0, 1] the best scale, then the best share; 0 unless it lowers
    ``−2 log L`` by more than :data:`_SHAPE_EVIDENCE` × ``tau`` (the lateral residuals'
    autocorrelation time).  Each residual weighs by its own variance, so the lateral
    spread that the angle term already explains (its lever arm along a long segment)
    does not push the constant part to 0."""
    r2 = res.r[:, 0] ** 2

    def profile(share: float) -> float:
        def nll(log_var: float) -> float:
            v = res.variance(math.exp(log_var), var_rad, share)[:, 0]
            return float(np.sum(np.log(v) + r2 / v))

        best = minimize_scalar(nll, bounds=(_LOG_VAR_MIN, _LOG_VAR_MAX), method="bounded")
        return float(best.fun)

    shares = np.linspace(0.0, 1.0, _SHARE_GRID)
    m2ll = np.array([profile(float(f)) for f in shares])
    best = int(np.argmin(m2ll))
    return float(shares[best]) if m2ll[0] - m2ll[best] > _SHAPE_EVIDENCE * tau else 0.0


def _lag_pairs(res: _Residuals) -> list[tuple[IntArray, IntArray]]:
    """For each lag ``L`` = 1…:data:`_MAX_LAG`, the observations ``(j, k)`` of one wall
    ``L`` scans apart: they do not depend on the terms, so they are found once.

    A wall seen in two pieces in one scan (a door between them) has no single
    observation at that scan: its pieces err apart, and pairing one of them with the
    next scan's would read as a correlation lost in one scan.  Such (wall, scan) keys
    take no part in the sum.
    """
    keys = list(zip(res.wall.tolist(), res.step.tolist(), strict=True))
    seen: dict[tuple[int, int], int] = {}
    for j, key in enumerate(keys):
        seen[key] = -1 if key in seen else j
    out = []
    for lag in range(1, _MAX_LAG + 1):
        later = np.array([seen.get((w, k + lag), -1) if seen[(w, k)] >= 0 else -1 for w, k in keys])
        first = np.flatnonzero(later >= 0)
        out.append((first, later[first]))
    return out


def _iact(
    res: _Residuals,
    pairs: list[tuple[IntArray, IntArray]],
    var_m: float,
    var_rad: float,
    share: float = 0.0,
) -> tuple[float, float]:
    """τ per dof of the whitened residuals of one wall ``L`` scans apart (``pairs``:
    :func:`_lag_pairs`)."""
    z = res.whitened(var_m, var_rad, share)
    taus = []
    for d in range(2):
        tau = 1.0
        for first, later in pairs:
            a, b = z[first, d], z[later, d]
            if a.size < 2 or np.std(a) == 0.0 or np.std(b) == 0.0:
                break
            rho = float(np.corrcoef(a, b)[0, 1])
            if not rho > MIN_CORRELATION:
                break
            tau += 2.0 * rho
        taus.append(tau)
    return taus[0], taus[1]


def estimate_line_model_error(
    log: MeasurementLog,
    params: FloorPlanParams | None = None,
    *,
    correlated: bool = True,
    shape: LineModelShape = "constant",
) -> LineModelError:
    """The line model-error terms of ``log`` (module docstring).

    ``correlated=False`` stops at step 1: each observation whitened to 1 as if
    consecutive scans erred independently (``iact`` is still measured, with those
    terms, and reported).  ``shape="length"`` splits the σ on ``ρ`` into a constant
    part and one falling as ``1/L`` (:class:`LineTerms`).

    ``log`` needs a reference trajectory, and its line covariances must hold no
    model-error term yet (extracted with ``line_model_sigma_m = line_model_sigma_rad
    = 0``).  ``params`` builds the plan (its survey σ is ignored).  Raises
    :class:`ValueError` without a reference or with fewer than
    :data:`MIN_OBSERVATIONS` line observations on plan walls.
    """
    check_choice("estimate_line_model_error", "shape", shape, get_args(LineModelShape))
    if log.true_poses is None:
        raise ValueError(
            "the line model error is estimated against a reference trajectory; the log has none"
        )
    p = FloorPlanParams() if params is None else params
    p = replace(p, survey_sigma_m=_NEGLIGIBLE_SURVEY, survey_sigma_rad=_NEGLIGIBLE_SURVEY)
    res = _residuals(log, build_floor_plan(log, p))
    n = int(res.r.shape[0])
    if n < MIN_OBSERVATIONS:
        raise ValueError(
            f"{n} line observations lie on walls of the log's floor plan; the line "
            f"model error needs at least {MIN_OBSERVATIONS}"
        )
    z0 = res.whitened(0.0, 0.0)
    without = (float(np.mean(z0[:, 0] ** 2)), float(np.mean(z0[:, 1] ** 2)))
    pairs = _lag_pairs(res)
    share = 0.0
    gate = _variances(res, (1.0, 1.0))
    if shape == "length":
        share = _length_share(res, gate[1], _iact(res, pairs, *gate)[0])
        if share > 0.0:
            gate = _variances(res, (1.0, 1.0), share)
    var_m, var_rad = gate
    tau = _iact(res, pairs, var_m, var_rad, share)
    for _ in range(_MAX_ROUNDS if correlated else 0):
        # τ moves with the terms (they reweight the observations): to a fixed point.
        var_m, var_rad = _variances(res, (1.0 / tau[0], 1.0 / tau[1]), share)
        last, tau = tau, _iact(res, pairs, var_m, var_rad, share)
        if max(abs(a - b) / b for a, b in zip(tau, last, strict=True)) < _TAU_TOL:
            break
    terms = LineTerms.from_split(var_m, var_rad, share)
    gate_terms = LineTerms.from_split(*gate, share)
    return LineModelError(
        sigma_m=terms.sigma_m,
        sigma_rad=terms.sigma_rad,
        iact=tau,
        observations=n,
        nees_without=without,
        gate_sigma_m=gate_terms.sigma_m,
        gate_sigma_rad=gate_terms.sigma_rad,
        correlated=correlated,
        sigma_m_metre=terms.sigma_m_metre,
        gate_sigma_m_metre=gate_terms.sigma_m_metre,
        shape=shape,
    )


def with_line_model_error(
    log: MeasurementLog, terms: LineTerms, gate: LineTerms | None = None
) -> MeasurementLog:
    """``log`` with the model-error ``terms`` added to every line's covariance, as the
    extractor adds ``ExtractionParams.line_model_sigma_m`` and ``line_model_sigma_rad``
    (those two with ``sigma_m_metre = 0``).

    ``gate``, when given, makes the log's covariances for compatibility tests
    (:attr:`~mapfuse_core.measlog.MeasurementLog.feat_gate_cov`) the same lines with
    those terms instead (:attr:`LineModelError.gate_terms`): it is meant for a log whose
    lines hold no model-error term yet, as :func:`estimate_line_model_error` takes them.
    Without ``gate`` the terms are added to the log's own gate covariances too, if it
    has any.
    """
    if not isinstance(terms, LineTerms):
        raise TypeError(f"with_line_model_error: terms must be LineTerms, got {terms!r}")
    if gate is not None and not isinstance(gate, LineTerms):
        raise TypeError(f"with_line_model_error: gate must be LineTerms or None, got {gate!r}")
    lines = np.flatnonzero(log.feat_kind == int(FeatureKind.LINE)).tolist()
    lengths = (log.feat_extent[:, 1] - log.feat_extent[:, 0]).tolist()
    for i in lines:
        if not (math.isfinite(lengths[i]) and lengths[i] >= 0.0):
            raise ValueError(
                f"line feature {i} has extent {log.feat_extent[i].tolist()}: its length "
                "must be finite and >= 0 for the line model-error terms"
            )

    def added(base: FloatArray, t: LineTerms) -> FloatArray:
        cov = base.copy()
        for i in lines:
            cov[i] = cov[i] + t.cov(log.feat_params[i], lengths[i])
        return cov

    if gate is not None:
        gate_cov: FloatArray | None = added(log.feat_cov, gate)
    elif log.feat_gate_cov is not None:
        gate_cov = added(log.feat_gate_cov, terms)
    else:
        gate_cov = None
    return replace(log, feat_cov=added(log.feat_cov, terms), feat_gate_cov=gate_cov)


def _terms_text(t: LineTerms) -> str:
    """``t`` as a log's metadata states it (the two parts on ``ρ`` add as variances)."""
    part = f" and {t.sigma_m_metre:.3f} m / length in quadrature" if t.sigma_m_metre else ""
    return f"{t.sigma_m:.3f} m{part}, {math.degrees(t.sigma_rad):.2f} deg"


def _check_sigma(name: str, v: float) -> None:
    if not (math.isfinite(v) and v >= 0.0):
        raise ValueError(f"{name} must be finite and >= 0, got {v}")
