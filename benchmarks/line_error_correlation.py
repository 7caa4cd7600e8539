"""Whitened errors of the extracted lines on generated worlds, and their correlations.

Every line observation of a simulated drive that is labelled with a wall of the world
is compared with that wall in the sensor frame at the true pose
(:func:`mapfuse_core.models.line.line_residual`, as the estimators use it), and each
component (``offset``, ``angle``) is divided by the standard deviation the extractor
states for it (:func:`mapfuse_core.models.line.line_residual_cov`).  Prints one JSON
document: the mean and variance of each component, the mean NEES per degree of
freedom and the share above the χ²₂ 0.999 quantile; the correlation of two walls' errors
within one scan; and, for one wall, the correlation of its errors ``lag`` scans apart
(``--lags``).  An estimator that takes the observations as independent needs all of
those correlations near 0.

    PYTHONPATH=. python benchmarks/line_error_correlation.py --seeds 0 6 \\
        --world shape=figure8,laser_range_m=40,walls=22,trees=50,loop_length_m=400
"""

from __future__ import annotations

import argparse
import itertools
import json
from typing import Any

import numpy as np
from scipy.stats import chi2

from benchmarks.world_runs import truth_in_sensor, world_logs
from mapfuse.campaign.spec import parse_world_args
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.models.line import line_residual, line_residual_cov

DOFS = ("offset", "angle")


def whitened_lines(log: MeasurementLog) -> list[tuple[int, int, np.ndarray, float]]:
    """``(step, wall id, whitened error, NEES)`` of every line observation of a wall."""
    out = []
    for j in np.flatnonzero(log.feat_kind == int(FeatureKind.LINE)).tolist():
        truth = truth_in_sensor(log, j)
        if truth is None:
            continue
        e = line_residual(truth, log.feat_params[j])[0]
        S = line_residual_cov(truth, log.feat_params[j], log.feat_cov[j])
        nees = float(e @ np.linalg.solve(S, e))
        out.append((int(log.feat_step[j]), int(log.feat_true_id[j]), e / np.sqrt(np.diag(S)), nees))
    return out


def _corr(pairs: list[tuple[np.ndarray, np.ndarray]]) -> dict[str, Any]:
    if len(pairs) < 3:
        return {"pairs": len(pairs), **dict.fromkeys(DOFS)}
    P = np.array(pairs)
    return {
        "pairs": len(pairs),
        **{
            d: round(float(np.corrcoef(P[:, 0, k], P[:, 1, k])[0, 1]), 3)
            for k, d in enumerate(DOFS)
        },
    }


def summarise(obs: list[list[tuple[int, int, np.ndarray, float]]], lags: list[int]) -> dict:
    """Statistics over the drives (one list of observations per drive)."""
    flat = [o for drive in obs for o in drive]
    Z = np.array([o[2] for o in flat]).reshape(-1, 2)
    nees = np.array([o[3] for o in flat])
    within: list[tuple[np.ndarray, np.ndarray]] = []
    lagged: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {L: [] for L in lags}
    for drive in obs:
        by_step: dict[int, list[np.ndarray]] = {}
        by_wall: dict[tuple[int, int], np.ndarray] = {}
        for step, wall, z, _ in drive:
            by_step.setdefault(step, []).append(z)
            by_wall[(wall, step)] = z
        for zs in by_step.values():
            within += list(itertools.combinations(zs, 2))
        for (wall, step), z in by_wall.items():
            for L in lags:
                later = by_wall.get((wall, step + L))
                if later is not None:
                    lagged[L].append((z, later))
    q = float(chi2.ppf(0.999, 2))
    return {
        "observations": len(flat),
        "mean": {d: round(float(Z[:, k].mean()), 3) for k, d in enumerate(DOFS)},
        "variance": {d: round(float(Z[:, k].var(ddof=1)), 3) for k, d in enumerate(DOFS)},
        "nees_per_dof": round(float(nees.mean()) / 2.0, 3),
        "above_chi2_0999": round(float(np.mean(nees > q)), 5),
        "within_scan": _corr(within),
        "lagged": {str(L): _corr(v) for L, v in lagged.items()},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs=2, default=(0, 6), help="first, end")
    p.add_argument("--world", default="", help="generator keywords, key=value,...")
    p.add_argument("--lags", default="1,5,20", help="comma-separated scan lags")
    args = p.parse_args()
    world = parse_world_args(args.world) if args.world else {}
    lags = [int(v) for v in args.lags.split(",") if v]
    drives = [whitened_lines(log) for _, log in world_logs(world, range(*args.seeds), set())]
    out = {"world": args.world, "seeds": list(range(*args.seeds)), **summarise(drives, lags)}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
