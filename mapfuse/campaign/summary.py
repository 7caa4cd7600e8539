"""A campaign's statistics per estimator and fusion setting: :func:`summarise`.

Reads a campaign directory (:class:`~mapfuse.campaign.store.CampaignStore`) and
gives, per (estimator, fusion), the ANEES series with its bounds, the RMSE per step,
and the per-run quantities with 95 % intervals (:class:`GroupSummary`).  Only runs
whose row is ``ok`` enter; failed rows are counted.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mapfuse.campaign.stats import (
    AneesSeries,
    Interval,
    anees_bounds,
    anees_series,
    mean_interval,
    proportion_interval,
    rmse_per_step,
    stack_runs,
)
from mapfuse.campaign.store import CampaignStore
from mapfuse.campaign.task import array_key
from mapfuse_core.geometry.se2 import FloatArray

__all__ = ["MAX_ERROR_LIMIT_M", "NEES_WITHIN_LIMIT", "GroupSummary", "summarise"]

#: Per-run criterion on the maximum position error (the paper's fused figure).
MAX_ERROR_LIMIT_M = 0.15
#: Per-run criterion on the fraction of steps with NEES ≤ χ²(3, 0.95).
NEES_WITHIN_LIMIT = 0.90


@dataclass(frozen=True, eq=False)
class GroupSummary:
    """One estimator with one fusion setting, over the campaign's runs."""

    estimator: str
    """Estimator name."""
    fusion: bool
    """Fusion setting."""
    seeds: tuple[int, ...]
    """Seeds of the runs that finished without error, ascending."""
    failed: tuple[int, ...]
    """Seeds whose row is an error."""
    errors: tuple[str, ...]
    """First line of each failed row's error, as :attr:`failed`."""
    anees: AneesSeries
    """ANEES per step over :attr:`seeds`."""
    timestamps: FloatArray
    """(T,) step times of the longest run (s)."""
    rmse: FloatArray
    """(T,) position RMSE per step over the runs (m)."""
    rows: tuple[Mapping[str, Any], ...]
    """The ok rows, as :attr:`seeds`."""

    def values(self, column: str) -> list[float]:
        """Non-missing values of a row column over the ok runs."""
        return [float(r[column]) for r in self.rows if r.get(column) is not None]

    def interval(self, column: str) -> Interval:
        """Mean over runs of ``column`` with its 95 % interval."""
        return mean_interval(self.values(column))

    @property
    def max_error_ok(self) -> Interval:
        """Fraction of runs with max error ≤ :data:`MAX_ERROR_LIMIT_M`."""
        v = self.values("max_m")
        return proportion_interval(sum(x <= MAX_ERROR_LIMIT_M for x in v), len(v))

    @property
    def nees_within_ok(self) -> Interval:
        """Fraction of runs with NEES within χ²(3, 0.95) on ≥ 90 % of their steps."""
        v = self.values("nees_within")
        return proportion_interval(sum(x >= NEES_WITHIN_LIMIT for x in v), len(v))

    @property
    def anchor_anees(self) -> tuple[float, float, float, int]:
        """``(mean anchor NEES, lower bound, upper bound, runs with an anchor)``."""
        v = self.values("anchor_nees")
        if not v:
            return math.nan, math.nan, math.nan, 0
        lo, hi = anees_bounds(len(v))
        return float(np.mean(v)), float(lo), float(hi), len(v)

    @property
    def wrong_pairings(self) -> tuple[int, int]:
        """``(wrong pairings accepted in all runs, runs with at least one)``."""
        v = [int(x) for x in self.values("wrong_pairings")]
        return sum(v), sum(x > 0 for x in v)

    @property
    def max_error_quantiles(self) -> tuple[float, float, float]:
        """Median, 90th percentile and maximum of the per-run max error (m)."""
        v = self.values("max_m")
        if not v:
            return math.nan, math.nan, math.nan
        return (
            float(np.median(v)),
            float(np.quantile(v, 0.9)),
            float(np.max(v)),
        )


def _group(
    rows: Sequence[Mapping[str, Any]],
    estimator: str,
    fusion: bool,
    arrays: Mapping[int, Mapping[str, np.ndarray]],
) -> GroupSummary:
    mine = sorted(
        (r for r in rows if r["estimator"] == estimator and bool(r["fusion"]) is fusion),
        key=lambda r: r["seed"],
    )
    ok = [r for r in mine if r["status"] == "ok"]
    bad = [r for r in mine if r["status"] != "ok"]
    nees, pos, times = [], [], []
    for r in ok:
        a = arrays[r["seed"]]
        nees.append(a[array_key(estimator, fusion, "nees")])
        pos.append(a[array_key(estimator, fusion, "position_error")])
        times.append(a.get("timestamps", np.arange(len(pos[-1]), dtype=float)))
    nees_m = stack_runs(nees)
    longest = max(times, key=len) if times else np.zeros(0)
    return GroupSummary(
        estimator=estimator,
        fusion=fusion,
        seeds=tuple(r["seed"] for r in ok),
        failed=tuple(r["seed"] for r in bad),
        errors=tuple(str(r.get("error") or "").splitlines()[0] for r in bad),
        anees=anees_series(nees_m if nees else np.zeros((0, 0))),
        timestamps=np.asarray(longest[: nees_m.shape[1]], dtype=float),
        rmse=rmse_per_step(stack_runs(pos)),
        rows=tuple(ok),
    )


def summarise(store: CampaignStore | str) -> list[GroupSummary]:
    """Every (estimator, fusion) of the stored spec, in its order (fusion first)."""
    store = store if isinstance(store, CampaignStore) else CampaignStore(Path(store))
    spec = store.spec()
    rows = store.rows()
    seeds = sorted({r["seed"] for r in rows if r["status"] == "ok"})
    arrays = {s: store.arrays(s) for s in seeds}
    return [_group(rows, e, f, arrays) for f in spec.fusions for e in spec.estimators]
