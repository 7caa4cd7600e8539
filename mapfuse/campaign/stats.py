"""Statistics over a campaign's runs: ANEES with Bar-Shalom's χ² bounds, RMSE per
step, and 95 % confidence intervals.

With ``N`` runs of a consistent estimator, ``N·ANEES`` at one step is χ² with ``3N``
degrees of freedom (the runs' errors are independent), so ANEES lies inside
``[χ²₃ₙ(0.025)/N, χ²₃ₙ(0.975)/N]`` with probability 0.95 at every step.  Steps where
a run has no NEES (a singular covariance, a shorter run) count fewer runs there; the
bounds use the count of each step.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.stats import beta, chi2, t

from mapfuse_core.geometry.se2 import FloatArray

__all__ = [
    "AneesSeries",
    "Interval",
    "anees_bounds",
    "anees_series",
    "mean_interval",
    "proportion_interval",
    "rmse_per_step",
    "stack_runs",
]


def anees_bounds(
    n_runs: int | np.ndarray, dof: int = 3, p: float = 0.95
) -> tuple[FloatArray, FloatArray]:
    """Two-sided ``p`` bounds of the ANEES of ``n_runs`` consistent runs:
    ``χ²_{dof·N}((1−p)/2)/N`` and ``χ²_{dof·N}((1+p)/2)/N`` (arrays like ``n_runs``;
    NaN where ``n_runs`` is 0)."""
    n = np.asarray(n_runs, dtype=float)
    if np.any(n < 0) or not 0.0 < p < 1.0 or dof < 1:
        raise ValueError(f"need n_runs >= 0, dof >= 1 and 0 < p < 1; got {n_runs}, {dof}, {p}")
    with np.errstate(invalid="ignore", divide="ignore"):
        safe = np.where(n > 0, n, np.nan)
        lo = chi2.ppf((1.0 - p) / 2.0, dof * safe) / safe
        hi = chi2.ppf((1.0 + p) / 2.0, dof * safe) / safe
    return np.asarray(lo, dtype=float), np.asarray(hi, dtype=float)


def stack_runs(series: Sequence[np.ndarray]) -> FloatArray:
    """(R, T) array of per-run series (T: the longest), NaN-padded."""
    if not series:
        return np.zeros((0, 0))
    width = max(len(s) for s in series)
    out = np.full((len(series), width), np.nan)
    for i, s in enumerate(series):
        out[i, : len(s)] = s
    return out


@dataclass(frozen=True, eq=False)
class AneesSeries:
    """ANEES per step over runs, with its bounds."""

    anees: FloatArray
    """(T,) mean NEES over the runs with a NEES at each step (NaN: none)."""
    runs: np.ndarray
    """(T,) number of runs at each step."""
    lower: FloatArray
    """(T,) lower two-sided bound at each step."""
    upper: FloatArray
    """(T,) upper bound."""
    p: float
    """Probability of the bounds."""
    dof: int
    """Degrees of freedom of one NEES."""

    @property
    def valid(self) -> np.ndarray:
        """(T,) steps with at least one run."""
        return self.runs > 0

    @property
    def inside(self) -> np.ndarray:
        """(T,) steps whose ANEES is inside its bounds (False where no run)."""
        with np.errstate(invalid="ignore"):
            return self.valid & (self.anees >= self.lower) & (self.anees <= self.upper)

    @property
    def fraction_inside(self) -> float:
        """Fraction of the valid steps inside the bounds (NaN without any)."""
        v = int(self.valid.sum())
        return float(self.inside.sum() / v) if v else math.nan

    @property
    def fraction_above(self) -> float:
        """Fraction of the valid steps above the upper bound (optimism)."""
        v = int(self.valid.sum())
        with np.errstate(invalid="ignore"):
            return float(np.sum(self.valid & (self.anees > self.upper)) / v) if v else math.nan

    @property
    def overall(self) -> float:
        """Mean of the ANEES over the valid steps: 3 for a consistent estimator."""
        return float(np.mean(self.anees[self.valid])) if self.valid.any() else math.nan


def anees_series(nees: np.ndarray, dof: int = 3, p: float = 0.95) -> AneesSeries:
    """ANEES per step of ``nees`` (R runs, T steps; NaN: no NEES there)."""
    x = np.asarray(nees, dtype=float)
    if x.ndim != 2:
        raise ValueError(f"nees must be (runs, steps), got shape {x.shape}")
    finite = np.isfinite(x)
    runs = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        anees = np.where(runs > 0, np.where(finite, x, 0.0).sum(axis=0) / runs, np.nan)
    lo, hi = anees_bounds(runs, dof, p)
    return AneesSeries(anees=anees, runs=runs, lower=lo, upper=hi, p=p, dof=dof)


def rmse_per_step(errors: np.ndarray) -> FloatArray:
    """(T,) root mean square over runs of (R, T) errors (NaN-padded runs skipped)."""
    x = np.asarray(errors, dtype=float)
    finite = np.isfinite(x)
    n = finite.sum(axis=0)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, np.sqrt(np.where(finite, x * x, 0.0).sum(axis=0) / n), np.nan)


@dataclass(frozen=True)
class Interval:
    """An estimate with a two-sided confidence interval."""

    value: float
    """The estimate (NaN without data)."""
    low: float
    """Lower end."""
    high: float
    """Upper end."""
    n: int
    """Number of values behind it."""

    def text(self, digits: int = 3, scale: float = 1.0) -> str:
        """``value [low, high]``, or ``n/a``."""
        if not math.isfinite(self.value):
            return "n/a"
        v, lo, hi = (scale * x for x in (self.value, self.low, self.high))
        if not (math.isfinite(lo) and math.isfinite(hi)):
            return f"{v:.{digits}f}"
        return f"{v:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def mean_interval(values: Sequence[float] | np.ndarray, p: float = 0.95) -> Interval:
    """Mean of ``values`` (NaN and None dropped) with its Student-t interval."""
    x = np.asarray([v for v in values if v is not None], dtype=float)
    x = x[np.isfinite(x)]
    n = int(x.size)
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    m = float(x.mean())
    if n == 1:
        return Interval(m, math.nan, math.nan, 1)
    half = float(t.ppf((1 + p) / 2, n - 1) * x.std(ddof=1) / math.sqrt(n))
    return Interval(m, m - half, m + half, n)


def proportion_interval(successes: int, n: int, p: float = 0.95) -> Interval:
    """Proportion ``successes / n`` with its Clopper–Pearson (exact) interval."""
    if n < 0 or not 0 <= successes <= n:
        raise ValueError(f"need 0 <= successes <= n, got {successes} of {n}")
    if n == 0:
        return Interval(math.nan, math.nan, math.nan, 0)
    a = (1 - p) / 2
    lo = 0.0 if successes == 0 else float(beta.ppf(a, successes, n - successes + 1))
    hi = 1.0 if successes == n else float(beta.ppf(1 - a, successes + 1, n - successes))
    return Interval(successes / n, lo, hi, n)
