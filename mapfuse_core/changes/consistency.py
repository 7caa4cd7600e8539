"""Whether a run can be trusted to judge its known map: :class:`RunConsistency`.

Change detection tests every known feature against the run's evidence with the run's
own covariances (:mod:`mapfuse_core.changes.classify`).  A run whose errors are far
larger than its covariances say puts the walls it saw late in the wrong place with
too small an uncertainty, and the χ² tests then call standing walls moved
(``docs/change-detection.md``).  So the run's own consistency is judged first, from the best
evidence it has:

* ``"reference NEES"``: with a reference trajectory (simulation, a corrected CARMEN
  log), the mean pose NEES over the run against the two-sided 95 % acceptance region
  of a consistent estimator's mean, which allows for the series' autocorrelation
  (:func:`mapfuse_core.evaluation.run_consistency.consistency_from_nees`: the reference
  is the evaluation's);
* ``"innovations"``: without one, the χ² of the filter's observation innovations summed
  over the run against the two-sided 95 % region of a χ² with their degrees of freedom
  (a consistent filter's innovations are white, so the sum is χ²; the association's
  gate truncates the largest, which only lowers it);
* ``"none"``: no such evidence (an estimator that reports neither).

A run above the region's upper end is not trusted: :func:`withhold_changes` then makes
the report inconclusive, and no feature is called moved, missing or new.  A run below
its lower end is pessimistic, not misplaced, and is trusted.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from scipy.stats import chi2

from mapfuse_core.changes.report import ChangeReport, ChangeStatus

__all__ = [
    "EVIDENCE",
    "LEVEL",
    "RunConsistency",
    "consistency_from_innovations",
    "no_consistency_evidence",
    "withhold_changes",
]

Evidence = Literal["reference NEES", "innovations", "none"]

#: Every :attr:`RunConsistency.evidence`.
EVIDENCE: tuple[str, ...] = ("reference NEES", "innovations", "none")

#: Probability of the two-sided acceptance regions.
LEVEL = 0.95


@dataclass(frozen=True)
class RunConsistency:
    """How consistent a run is, and whether change detection may trust it."""

    evidence: Evidence
    """What the verdict rests on (module docstring)."""
    statistic: float
    """Reference NEES: the mean pose NEES (3 dof).  Innovations: their χ² summed over
    the run, divided by its degrees of freedom.  NaN without evidence."""
    low: float
    """Lower end of the two-sided 95 % region of :attr:`statistic` for a consistent
    run (NaN without evidence)."""
    high: float
    """Upper end; a run above it is not trusted (NaN without evidence)."""
    samples: float
    """Reference NEES: effective independent samples of the mean.  Innovations:
    degrees of freedom.  0 without evidence."""

    @property
    def trusted(self) -> bool:
        """Whether the run is not overconfident: its statistic is at most
        :attr:`high` (or there is no evidence either way)."""
        return self.evidence == "none" or not self.statistic > self.high

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready form."""
        return {
            "evidence": self.evidence,
            "statistic": _num(self.statistic),
            "interval_95": [_num(self.low), _num(self.high)],
            "samples": _num(self.samples),
            "trusted": self.trusted,
        }


def consistency_from_innovations(chi2_sum: float, dof: int) -> RunConsistency:
    """The verdict of a filter's observation innovations: ``chi2_sum`` their χ² summed
    over the run, ``dof`` its degrees of freedom (no evidence when 0)."""
    if isinstance(dof, bool) or not isinstance(dof, int | np.integer) or dof < 0:
        raise ValueError(f"dof must be an int >= 0, got {dof!r}")
    if not (math.isfinite(chi2_sum) and chi2_sum >= 0.0):
        raise ValueError(f"chi2_sum must be finite and >= 0, got {chi2_sum!r}")
    if dof == 0:
        return no_consistency_evidence()
    lo = float(chi2.ppf(0.5 * (1.0 - LEVEL), dof)) / dof
    hi = float(chi2.ppf(0.5 * (1.0 + LEVEL), dof)) / dof
    return RunConsistency(
        evidence="innovations",
        statistic=float(chi2_sum) / dof,
        low=lo,
        high=hi,
        samples=float(dof),
    )


def no_consistency_evidence() -> RunConsistency:
    """The verdict of a run that reports no consistency evidence: trusted, for want
    of a reason not to."""
    nan = math.nan
    return RunConsistency(evidence="none", statistic=nan, low=nan, high=nan, samples=0.0)


def withhold_changes(report: ChangeReport, consistency: RunConsistency) -> ChangeReport:
    """``report`` with its run's verdict; when the run is not trusted, every feature
    classified moved or missing becomes inconclusive and no landmark is reported new
    (their evidence stays in the per-feature entries).  Confirmed and unobserved
    features keep their class: neither claims a change."""
    if consistency.trusted:
        return dataclasses.replace(report, consistency=consistency)
    claims = (ChangeStatus.MOVED, ChangeStatus.MISSING)
    known = tuple(
        dataclasses.replace(c, status=ChangeStatus.INCONCLUSIVE) if c.status in claims else c
        for c in report.known
    )
    return dataclasses.replace(
        report, known=known, new=(), withheld_new=len(report.new), consistency=consistency
    )


def _num(v: float) -> float | None:
    f = float(v)
    return f if math.isfinite(f) else None
