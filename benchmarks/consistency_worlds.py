"""Consistency over generated worlds, and how much of any excess the circle bias explains.

For every seed a world is generated (``--world``, the generator's keywords; by default
figure-eights with a 40 m laser and mixed walls and trees) and simulated once.  Each
estimator then runs, with and without fusion, on two versions of the same log:

* ``as simulated``: the extractor's observations;
* ``circles unbiased``: every circle observation of a world tree replaced by the true
  circle in the sensor frame plus noise drawn from the observation's own stated
  covariance (seeded by the run's seed), so circles are exactly as the models assume;
  lines and spurious detections are left as they are (a draw with a radius ≤ 0 is
  drawn again).

The difference between the two is the part of the estimators' NEES that the circle
extraction's bias causes (``docs/results/known-gaps.md``: trunks are measured slightly too
close and too thin).  Output: one JSON line per seed, estimator, fusion and version
(``--out``), then a JSON summary on stdout with the ANEES over the runs, the fraction of
steps inside its two-sided 95 % bounds, and the anchor ANEES with its bounds.

    PYTHONPATH=. python benchmarks/consistency_worlds.py --seeds 1 13 --out /tmp/cw.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from typing import Any

import numpy as np

from benchmarks.world_runs import append_rows, read_rows, world_logs
from mapfuse.campaign.spec import parse_world_args
from mapfuse.campaign.stats import anees_bounds, anees_series, mean_interval
from mapfuse.figures import run_errors
from mapfuse.runner import run
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.geometry.se2 import compose, inverse
from mapfuse_core.measlog import MeasurementLog

DEFAULT_WORLD = "shape=figure8,laser_range_m=40,walls=22,trees=50,loop_length_m=400"


def unbiased_circles(log: MeasurementLog, seed: int) -> MeasurementLog:
    """``log`` with every circle observation of a world circle redrawn from the truth
    with its stated covariance (lines and unlabelled detections unchanged)."""
    assert log.world is not None
    assert log.true_poses is not None
    world = {
        int(i): p
        for i, k, p in zip(log.world.ids, log.world.kinds, log.world.params, strict=True)
        if int(k) == int(FeatureKind.CIRCLE)
    }
    rng = np.random.default_rng(np.random.SeedSequence([seed, 7]))
    params = np.array(log.feat_params, copy=True)
    for j in np.nonzero(log.feat_kind == int(FeatureKind.CIRCLE))[0]:
        c = world.get(int(log.feat_true_id[j]))
        if c is None:
            continue
        pose = log.true_poses[int(log.feat_step[j])]
        centre = compose(inverse(pose), np.array([c[0], c[1], 0.0]))[:2]
        truth = np.array([centre[0], centre[1], c[2]])
        draw = rng.multivariate_normal(truth, log.feat_cov[j])
        while draw[2] <= 0.0:  # a radius must stay positive: redraw (truncated tail)
            draw = rng.multivariate_normal(truth, log.feat_cov[j])
        params[j] = draw
    return dataclasses.replace(log, feat_params=params)


def _rows(log: MeasurementLog, seed: int, version: str, estimators: list[str]) -> list[dict]:
    out = []
    assert log.true_poses is not None
    for fusion in (True, False):
        upstream = None
        for name in estimators:
            kw: dict[str, Any] = {} if name == "ekf" else {"upstream": upstream}
            t0 = time.perf_counter()
            r = run(log, name, fusion=fusion, **kw)
            if name == "ekf":
                upstream = r.result
            dx, nees = run_errors(r)
            anchor_nees = None if r.metrics.anchor is None else r.metrics.anchor.nees
            out.append(
                {
                    "seed": seed,
                    "version": version,
                    "estimator": name,
                    "fusion": fusion,
                    "nees": nees.tolist(),
                    "nees_mean": float(np.nanmean(nees)),
                    "anchor_nees": anchor_nees,
                    "rmse_m": float(np.sqrt(np.mean(np.sum(dx[:, :2] ** 2, axis=1)))),
                    "wall_s": time.perf_counter() - t0,
                }
            )
    return out


def summarise(rows: list[dict]) -> list[dict]:
    """ANEES statistics per (version, estimator, fusion)."""
    out = []
    keys = sorted({(r["version"], r["estimator"], r["fusion"]) for r in rows})
    for version, est, fusion in keys:
        sel = [
            r for r in rows if (r["version"], r["estimator"], r["fusion"]) == (version, est, fusion)
        ]
        steps = min(len(r["nees"]) for r in sel)
        a = anees_series(np.array([r["nees"][:steps] for r in sel]))
        anchors = [r["anchor_nees"] for r in sel if r["anchor_nees"] is not None]
        lo, hi = (
            (math.nan, math.nan)
            if not anchors
            else tuple(
                float(np.ravel(b)[0]) for b in anees_bounds(np.array([len(anchors)]), 3, 0.95)
            )
        )
        am = mean_interval([r["nees_mean"] for r in sel])
        out.append(
            {
                "version": version,
                "estimator": est,
                "fusion": fusion,
                "runs": len(sel),
                "anees": round(a.overall, 3),
                "anees_bounds": [round(float(a.lower[-1]), 3), round(float(a.upper[-1]), 3)],
                "steps_inside": round(a.fraction_inside, 3),
                "steps_above": round(a.fraction_above, 3),
                "run_nees_mean": [round(am.value, 3), round(am.low, 3), round(am.high, 3)],
                "anchor_anees": round(float(np.mean(anchors)), 3) if anchors else None,
                "anchor_bounds": [round(lo, 3), round(hi, 3)],
                "anchor_runs": len(anchors),
            }
        )
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--seeds", type=int, nargs=2, default=(1, 13), help="first, end (exclusive)")
    p.add_argument("--world", default=DEFAULT_WORLD, help="generator keywords, key=value,...")
    p.add_argument("--estimators", default="ekf,batch,isam2,fixedlag")
    p.add_argument("--out", required=True, help="JSON lines, appended to (resumes by seed)")
    args = p.parse_args()
    world = parse_world_args(args.world)
    estimators = args.estimators.split(",")
    rows = read_rows(args.out)
    for seed, log in world_logs(world, range(*args.seeds), {r["seed"] for r in rows}):
        new = _rows(log, seed, "as simulated", estimators)
        new += _rows(unbiased_circles(log, seed), seed, "circles unbiased", estimators)
        append_rows(args.out, new)
        rows += new
    print(
        json.dumps(
            {"world": world, "seeds": list(range(*args.seeds)), "groups": summarise(rows)}, indent=1
        )
    )


if __name__ == "__main__":
    main()
