"""What a run's numbers alone do not say: the ``matching`` block and the ``warnings``
list of ``metrics.json`` (``docs/warnings.md``).

A run can finish with plausible numbers and still be degraded: fusion asked for and
never achieved, a known map whose walls cannot be told apart along their length, a
vehicle estimate inconsistent with its own covariance.  :func:`run_warnings` looks
at the run's :class:`~mapfuse_core.estimate.EstimatorResult` and its log, once, for every
estimator, and says so in one sentence per case.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from mapfuse_core.estimate import (
    EstimatorResult,
    MatchAttempts,
    MatchingMetrics,
    NeesSummary,
)
from mapfuse_core.evaluation import CHI2_3_95
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray
from mapfuse_core.measlog import MeasurementLog

__all__ = [
    "NEES_MEAN_LIMIT",
    "NEES_WITHIN_LIMIT",
    "matching_block",
    "matching_of",
    "run_warnings",
]

#: Mean vehicle NEES (3 dof) above which a run is reported inconsistent: twice the
#: mean of a consistent estimator, more than two run-to-run standard deviations of a
#: consistent run's mean on loop600 (``docs/warnings.md``).
NEES_MEAN_LIMIT = 6.0

#: Fraction of steps with the vehicle NEES within χ²(3, 0.95) below which a run is
#: reported inconsistent (a consistent estimator has 0.95 on average).
NEES_WITHIN_LIMIT = 0.8


def matching_of(result: EstimatorResult) -> tuple[MatchAttempts | None, str | None]:
    """The map matchings behind ``result``'s anchor and the estimator that made them:
    the run's own, else those of the run it took its anchor from (a graph backend
    consuming the EKF's decisions); ``(None, None)`` when neither matched."""
    if result.matching is not None:
        return result.matching, result.estimator
    up = result.upstream
    if up is not None and up.matching is not None:
        return up.matching, up.estimator
    return None, None


def matching_block(result: EstimatorResult) -> MatchingMetrics:
    """Whether fusion was requested (on a log with a known map) and achieved (an
    anchor), and the CCDA calls behind it."""
    m, by = matching_of(result)
    return MatchingMetrics(
        requested=bool(result.fusion),
        achieved=result.anchor is not None,
        ccda_by=by,
        ccda_attempts=None if m is None else int(m.attempts),
        ccda_reasons=None if m is None else {k: int(v) for k, v in sorted(m.reasons.items())},
        search_limit=None if m is None else m.search_limit,
    )


def _reasons_text(reasons: Mapping[str, int]) -> str:
    return ", ".join(f"{k} {v}" for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]))


def _no_match(result: EstimatorResult) -> str | None:
    if not result.fusion or result.anchor is not None:
        return None
    m, by = matching_of(result)
    if m is None:
        how = "no map matching was made"
    elif m.attempts == 0:
        how = f"{by} made no CCDA attempt (too few well-observed features)"
    else:
        how = f"{by}'s {m.attempts} CCDA attempts ended: {_reasons_text(m.reasons)}"
    return (
        f"fusion requested, no match found: {how}; the run is SLAM without the known map "
        "(metrics.json 'matching')"
    )


def _no_extents(result: EstimatorResult, log: MeasurementLog) -> str | None:
    km = log.known_map
    if not result.fusion or len(km) == 0:
        return None
    lines = np.asarray(km.kinds) == int(FeatureKind.LINE)
    if not np.any(lines):
        return None
    if km.extents is None:
        missing = int(np.sum(lines))
    else:
        ext = np.asarray(km.extents, dtype=float)[lines]
        missing = int(np.sum(~np.all(np.isfinite(ext), axis=1)))
    if missing == 0:
        return None
    return (
        f"known map without extents (known_extents) for {missing} of its "
        f"{int(np.sum(lines))} lines: collinear known walls cannot be told apart, anchor "
        "accuracy can degrade"
    )


def _inconsistent(nees: NeesSummary, covs: FloatArray) -> list[str]:
    out = []
    n_steps = int(covs.shape[0])
    # A pose whose covariance is exactly zero is the frame's origin (step 0 of a filter
    # in Wglobal): its NEES is undefined by construction, not a fault.
    origin = int(np.sum(np.all(covs.reshape(n_steps, -1) == 0.0, axis=1)))
    bad = n_steps - nees.steps - origin
    if bad > 0:
        out.append(
            f"vehicle NEES not finite on {bad} of {n_steps} steps (a covariance that is "
            "not finite or not positive definite)"
        )
    mean, within = nees.mean, nees.fraction_within_chi2_95
    if mean > NEES_MEAN_LIMIT or within < NEES_WITHIN_LIMIT:
        out.append(
            f"estimator inconsistent on this run: vehicle NEES mean {mean:.2f} (3 if "
            f"consistent, warned above {NEES_MEAN_LIMIT:g}), within χ²(3, 0.95) = "
            f"{CHI2_3_95:.3f} on {100 * within:.1f} % of steps (95 % if consistent, warned "
            f"below {100 * NEES_WITHIN_LIMIT:g} %)"
        )
    return out


def run_warnings(
    result: EstimatorResult,
    log: MeasurementLog,
    nees: NeesSummary | None = None,
    covs: FloatArray | None = None,
) -> list[str]:
    """Every warning of a run, one sentence each (``docs/warnings.md``).

    ``nees``: the run's NEES against truth, ``None`` without truth; ``covs``: the
    (N, 3, 3) covariances it was computed from (default the result's main track).
    """
    out = [w for w in (_no_extents(result, log), _no_match(result)) if w is not None]
    if nees is None:
        return out
    if not math.isfinite(nees.mean):
        out.append(
            f"vehicle NEES not finite on any of the {result.n_steps} steps (a covariance "
            "that is not finite or not positive definite)"
        )
        return out
    covs = np.asarray(result.covs if covs is None else covs, dtype=float)
    return out + _inconsistent(nees, covs)
