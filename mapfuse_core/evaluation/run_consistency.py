"""A run's consistency verdict from its pose NEES against a reference trajectory
(:class:`mapfuse_core.changes.consistency.RunConsistency`, the evidence change
detection rests on)."""

from __future__ import annotations

import numpy as np

from mapfuse_core.changes.consistency import LEVEL, RunConsistency, no_consistency_evidence
from mapfuse_core.evaluation.nees import nees_mean_interval
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["consistency_from_nees"]


def consistency_from_nees(nees: FloatArray) -> RunConsistency:
    """The verdict of a run's pose NEES series (3 dof) against its reference; steps
    with a non-finite NEES (no estimate yet) are left out."""
    v = np.asarray(nees, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        return no_consistency_evidence()
    iv = nees_mean_interval(v, dof=3, p=LEVEL)
    lo, hi = iv.interval_95
    return RunConsistency(
        evidence="reference NEES",
        statistic=float(v.mean()),
        low=float(lo),
        high=float(hi),
        samples=float(iv.effective_samples),
    )
