"""How often a consistent estimator would pass the paper's per-seed criteria (prints JSON).

The batch smoother's joint covariance of every ``--stride``-th pose says how its
errors would scatter if it were consistent.  Drawing errors from it gives, per seed,
the probability that a consistent smoother with exactly this covariance fails

* "NEES ≤ χ²(3, 0.95) on at least 90 % of the steps", and
* "maximum position error ≤ 0.15 m",

and, from the anchor's covariance (the EKF's and the batch's), the probability that an
anchor consistent with it misses "≤ 0.04 m and ≤ 0.002 rad",

next to the observed values, and the distribution of the run's mean NEES
(:func:`mapfuse_core.evaluation.nees_mean_distribution`).  Only every ``stride``-th
step enters; errors persist for hundreds of steps, so the fraction is nearly that of
all steps, and the maximum is a slight underestimate of the maximum over all steps.
"""

from __future__ import annotations

import argparse
import json
from typing import Any

import numpy as np

from mapfuse.runner import run
from mapfuse_core.evaluation import (
    CHI2_3_95,
    anchor_truth,
    consistent_error_draws,
    joint_nees,
    nees_mean_distribution,
    nees_series,
    pose_errors,
    truth_in_global,
)
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate


def seed_row(seed: int, stride: int, draws: int) -> dict[str, Any]:
    """The row of loop600 seed ``seed``."""
    return log_row(simulate(load_scenario("loop600"), seed=seed).log, seed, stride, draws)


def log_row(log: MeasurementLog, seed: int, stride: int, draws: int) -> dict[str, Any]:
    """Observed values and consistent-estimator probabilities of one simulated run
    (``seed`` also seeds the draws)."""
    if log.true_poses is None:
        raise ValueError("the log has no true poses: a simulated run is needed")
    ekf = run(log, "ekf", fusion=True)
    batch = run(log, "batch", fusion=True, upstream=ekf.result, joint_stride=stride)
    joint = batch.result.details.joint_pose_cov
    assert joint is not None
    steps = joint.steps
    truth = truth_in_global(log.true_poses)
    err = pose_errors(batch.poses, truth)
    nees = nees_series(err.dx, batch.covs)[steps]
    dist = nees_mean_distribution(joint.cov)
    e = consistent_error_draws(joint.cov, draws, np.random.default_rng(seed))
    drawn_nees = joint_nees(e, joint.cov)
    within = np.mean(drawn_nees <= CHI2_3_95, axis=1)
    max_pos = np.max(np.hypot(e[:, :, 0], e[:, :, 1]), axis=1)
    m_ekf = ekf.metrics
    assert m_ekf.nees is not None
    assert m_ekf.position_error is not None
    anchor: dict[str, Any] = {}
    for name, a in (("ekf", ekf.result.anchor), ("batch", batch.result.anchor)):
        if a is None:
            anchor[name] = None
            continue
        d = a.x_Wknown_Wglobal - anchor_truth(log.true_poses, log.known_frame)
        ea = np.random.default_rng(seed).multivariate_normal(np.zeros(3), a.cov, size=draws)
        miss = (np.hypot(ea[:, 0], ea[:, 1]) > 0.04) | (np.abs(ea[:, 2]) > 0.002)
        anchor[name] = {
            "position_error_m": round(float(np.hypot(d[0], d[1])), 4),
            "heading_error_rad": round(abs(float(wrap_angle(d[2]))), 5),
            "p_consistent_anchor_misses": round(float(miss.mean()), 4),
        }
    return {
        "seed": seed,
        "batch": {
            "mean_nees": round(float(nees.mean()), 3),
            "model_mean_nees_sd": round(dist.sd, 3),
            "model_interval_95": [round(x, 3) for x in dist.interval],
            "equivalent_poses": round(dist.equivalent_poses, 2),
            "fraction_within": round(float(np.mean(nees <= CHI2_3_95)), 4),
            "max_position_error_m": round(float(err.position[steps].max()), 4),
        },
        "consistent_smoother_draws": {
            "draws": draws,
            "fraction_within_mean": round(float(within.mean()), 4),
            "p_fraction_within_below_0_9": round(float(np.mean(within < 0.9)), 4),
            "p_max_position_error_above_0_15": round(float(np.mean(max_pos > 0.15)), 4),
        },
        "ekf": {
            "fraction_within": round(m_ekf.nees.fraction_within_chi2_95, 4),
            "max_position_error_m": round(m_ekf.position_error.max, 4),
        },
        "anchor": anchor,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seeds", default="0-4", help="e.g. 0-4 or 1,3,7")
    ap.add_argument("--stride", type=int, default=10)
    ap.add_argument("--draws", type=int, default=20_000)
    args = ap.parse_args()
    if "-" in args.seeds:
        lo, hi = (int(x) for x in args.seeds.split("-"))
        seeds = list(range(lo, hi + 1))
    else:
        seeds = [int(x) for x in args.seeds.split(",")]
    rows = [seed_row(s, args.stride, args.draws) for s in seeds]
    print(json.dumps({"benchmark": "consistency_loop600", **summary(rows, args.stride)}, indent=1))


def summary(rows: list[dict[str, Any]], stride: int) -> dict[str, Any]:
    """The rows and the probability that a consistent estimator passes on all of them."""
    fails = [r["consistent_smoother_draws"] for r in rows]
    p_all_nees = float(np.prod([1.0 - f["p_fraction_within_below_0_9"] for f in fails]))
    p_all_max = float(np.prod([1.0 - f["p_max_position_error_above_0_15"] for f in fails]))
    anchors = [r["anchor"]["ekf"] for r in rows if r["anchor"]["ekf"] is not None]
    p_all_anchor = float(np.prod([1.0 - a["p_consistent_anchor_misses"] for a in anchors]))
    return {
        "stride": stride,
        "seeds": rows,
        "p_consistent_smoother_passes_nees_on_every_seed": round(p_all_nees, 3),
        "p_consistent_smoother_passes_max_on_every_seed": round(p_all_max, 3),
        "p_consistent_ekf_anchor_passes_on_every_seed": round(p_all_anchor, 3),
        "anchor_seeds": len(anchors),
    }


if __name__ == "__main__":
    main()
