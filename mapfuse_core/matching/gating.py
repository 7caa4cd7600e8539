"""Which pairings are worth a full test: the χ² gate, the pre-gate and the line gap.

Features are in the SPmap form of :mod:`mapfuse_core.geometry.features` (a line is its
reference point and direction ``(x, y, θ)``, a circle its centre and radius), all in
one frame.  A line's *extent* is the interval ``(t0, t1)`` it was seen on, along its
own direction from its reference point (NaN when unknown).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable

import numpy as np
from scipy.stats import chi2

from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import FloatArray, wrap_angle_half
from mapfuse_core.matching.config import AssociationConfig

__all__ = ["chi2_gate", "line_gap", "line_overhang", "near", "pregate"]


@functools.lru_cache(maxsize=64)
def chi2_gate(prob: float, dof: int) -> float:
    """χ² quantile of probability ``prob`` with ``dof`` degrees of freedom, cached (it
    is asked for once per observation)."""
    return float(chi2.ppf(prob, dof))


def line_gap(
    q_line: FloatArray,
    q_extent: tuple[float, float],
    t_line: FloatArray,
    t_extent: tuple[float, float],
) -> float:
    """Gap (m) along the target line between segment ``q`` and segment ``t``; 0 when
    they overlap or when an extent is unknown.

    ``q``'s end points are projected on the target line (the two lines are nearly
    collinear once they pass :func:`near`).  A query extent ``(0, 0)`` stands for the
    query's reference point alone.
    """
    if not all(math.isfinite(v) for v in (*q_extent, *t_extent)):
        return 0.0
    lo, hi = _projected(q_line, q_extent, t_line)
    return max(lo - t_extent[1], t_extent[0] - hi, 0.0)


def _projected(
    q_line: FloatArray, q_extent: tuple[float, float], t_line: FloatArray
) -> tuple[float, float]:
    """Segment ``q``'s ends projected on line ``t``: ``(lo, hi)`` along ``t`` from its
    reference point."""
    # Plain floats: this runs for every pre-gated pairing, where numpy's per-call
    # overhead on 2-vectors would be most of its time.
    qx, qy, qth = (float(v) for v in q_line)
    tx, ty, tth = (float(v) for v in t_line)
    cq, sq = math.cos(qth), math.sin(qth)
    ct, st = math.cos(tth), math.sin(tth)
    s0, s1 = ((qx + t * cq - tx) * ct + (qy + t * sq - ty) * st for t in q_extent)
    return min(s0, s1), max(s0, s1)


def line_overhang(
    q_line: FloatArray,
    q_extent: tuple[float, float],
    t_line: FloatArray,
    t_extent: tuple[float, float],
) -> float:
    """How far (m) segment ``q`` reaches beyond segment ``t``'s ends, along ``t``'s line:
    the larger of the two overhangs, 0 when ``q`` lies within ``t`` or when an extent is
    unknown.

    A segment of a wall lies within that wall: where ``t``'s extent is the wall's own
    (a surveyed wall), an overhang larger than the uncertainty of where the ends lie
    says ``q`` is another wall.  ``q``'s end points are projected on ``t``'s line.
    """
    if not all(math.isfinite(v) for v in (*q_extent, *t_extent)):
        return 0.0
    lo, hi = _projected(q_line, q_extent, t_line)
    return max(t_extent[0] - lo, hi - t_extent[1], 0.0)


def near(
    kind: FeatureKind, query: FloatArray, targets: FloatArray, max_dist: float, max_ang: float
) -> np.ndarray:
    """(n,) bool: which ``targets`` (n, 3) of ``kind`` pass the cheap pre-gate with ``query``.

    Circles: centre distance below ``max_dist``.  Lines: angle between them (modulo π)
    below ``max_ang`` and the offset of the query's reference point from the target's
    line below ``max_dist``: the lateral residual of the line model
    (:func:`mapfuse_core.models.line.line_residual`), for estimated and known lines alike.
    """
    targets = np.asarray(targets, dtype=float).reshape(-1, 3)
    dx, dy = targets[:, 0] - query[0], targets[:, 1] - query[1]
    if kind == FeatureKind.CIRCLE:
        out: np.ndarray = np.hypot(dx, dy) < max_dist
        return out
    lateral = np.abs(np.sin(targets[:, 2]) * dx - np.cos(targets[:, 2]) * dy)
    dang = np.abs(wrap_angle_half(targets[:, 2] - query[2]))
    ok: np.ndarray = (lateral < max_dist) & (dang < max_ang)
    return ok


def pregate(
    kind: FeatureKind,
    query: FloatArray,
    query_extent: tuple[float, float],
    targets: FloatArray,
    target_extent: Callable[[int], tuple[float, float]],
    config: AssociationConfig,
    max_gap: float | None = None,
) -> list[int]:
    """Rows of ``targets`` (n, 3) worth a χ² test with ``query``, in row order.

    :func:`near` with ``config``'s pre-gates, then, for lines, a :func:`line_gap` of at
    most ``max_gap`` (default ``config.line_gap_m``).  ``target_extent(row)`` gives a
    target line's extent; it is asked only for the rows that are near.
    """
    gap = config.line_gap_m if max_gap is None else max_gap
    ok = near(kind, query, targets, config.prefilter_m, config.prefilter_rad)
    rows: list[int] = np.nonzero(ok)[0].tolist()
    if kind == FeatureKind.CIRCLE:
        return rows
    return [k for k in rows if line_gap(query, query_extent, targets[k], target_extent(k)) <= gap]
