"""The laser's noise model as the fits need it, and the χ² acceptance bound.

A return at nominal bearing ``β`` has range ``ρ(β + δβ) + δρ``
(:mod:`mapfuse_core.sim.laser`).  Point-space fits weight a residual along a unit normal
by :func:`_normal_var`; range-space fits predict the mean and variance of each
measured range with :func:`_range_moments`, and those of where the beams stop hitting
a trunk with :func:`_edge_moments`.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import chi2 as chi2_dist
from scipy.stats import norm as norm_dist

from mapfuse_core.geometry.features import line_from_normal
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.perception.extraction.params import ExtractionParams


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


@functools.lru_cache(maxsize=64)
def _edge_moments(s: float) -> tuple[float, float]:
    """Mean and variance, in beam spacings, of a silhouette edge read from the beams.

    Beams ``Δβ`` apart sweep outwards across the tangent bearing ``τ`` of a trunk, each
    cast at its nominal bearing plus ``N(0, σβ²)``; ``s = σβ / Δβ``.  A beam hits while
    its cast bearing is inside ``τ``, and the cluster ends at the first beam ``K`` that
    misses.  The edge is read half a spacing beyond the last return,
    ``τ̂ = β_K − Δβ/2``.  Returns the mean of ``τ̂ − τ``, outwards positive (≤ 0: an
    inner beam that misses ends the cluster early), and its variance: sums over the
    beams of the exact probability that each is the first miss, averaged over 256 beam
    phases; 0 and ``1/12`` for ``s = 0``, −0.025 and 0.307 for the paper's ``s = ½``.
    """
    phase = (np.arange(256) + 0.5) / 256.0
    k = np.arange(-(10 * math.ceil(s) + 10), 10 * math.ceil(s) + 11)
    x = k[None, :] - phase[:, None]  # nominal bearing − τ, in spacings
    hit = norm_dist.cdf(-x / s) if s > 0.0 else (x < 0.0).astype(np.float64)
    survive = np.concatenate((np.ones((phase.size, 1)), np.cumprod(hit, axis=1)[:, :-1]), axis=1)
    p_first_miss = survive * (1.0 - hit)
    e = x - 0.5
    mean = float(np.mean(np.sum(p_first_miss * e, axis=1)))
    second = float(np.mean(np.sum(p_first_miss * e * e, axis=1)))
    return mean, second - mean * mean


@functools.lru_cache(maxsize=4096)
def _chi2_quantile(q: float, dof: int) -> float:
    return float(chi2_dist.ppf(q, max(dof, 1)))


def _chi2_max(params: ExtractionParams, dof: int) -> float:
    """Acceptance bound on a fit's χ² with ``dof`` degrees of freedom."""
    return _chi2_quantile(params.chi2_quantile, dof)


def line_model_cov(line: FloatArray, sigma_m: float, sigma_rad: float) -> FloatArray:
    """(3, 3) covariance the line model-error terms add to an observed line.

    ``line`` is an SPmap line ``(x, y, θ)`` in the sensor frame, y axis towards the
    sensor (:class:`~mapfuse_core.perception.extraction.ExtractedFeature`).  The terms
    are variances of its normal form: ``sigma_m²`` on the distance ``ρ`` from the
    sensor, ``sigma_rad²`` on the normal's direction ``α`` (rotating the line about
    the foot of that normal), propagated to ``(x, y, θ)`` at the line's origin.  The
    extractor adds it to every line (``ExtractionParams.line_model_sigma_m`` and
    ``line_model_sigma_rad``); :func:`~mapfuse_core.data.datasets.line_noise.with_line_model_error`
    adds it to the lines of a log already extracted, with the same result.
    """
    alpha = float(line[2]) - math.pi / 2.0
    ca, sa = math.cos(alpha), math.sin(alpha)
    rho = float(line[0]) * ca + float(line[1]) * sa
    t = -float(line[0]) * sa + float(line[1]) * ca
    _, J = line_from_normal(rho, alpha, t)
    Jm = J[:, :2]
    out: FloatArray = (Jm * np.array([sigma_m * sigma_m, sigma_rad * sigma_rad])) @ Jm.T
    return out
