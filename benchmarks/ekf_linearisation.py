"""The EKF linearised at the measured odometry against iterated through it (prints JSON).

``EKFConfig.odometry_linearisation``: ``"measured"`` (the paper's EKF) moves the map by
the measured increment and updates it there; ``"iterated"`` (the default) updates the
map before the motion and the increment together and relinearises the motion at the
updated increment.  The gap between the two is second order in a step's heading σ, so
the regimes vary that alone on ``loop600``'s world and drive:

* ``loop600``: the scenario as it is, a scan every 0.25 m (heading σ ≈ 0.0009 rad a
  step);
* ``rough``: a scan every 1 m (``dt_s`` 0.5, 600 steps for the 600 m loop) and a
  steering σ five times loop600's (2.5°): ≈ 0.017 rad a step, the lower end of the
  CARMEN logs' simulated odometry (``docs/results/carmen.md``);
* ``rougher``: the same with eight times loop600's steering σ (4°): ≈ 0.028 rad a step,
  their upper end.

Every seed simulates each regime once; both linearisations run on that log, with and
without fusion.  One JSON line per run, then per regime, linearisation and fusion the
ANEES (mean of the runs' mean NEES) with the two-sided 95 % region of a consistent
estimator from the runs' effective samples, the median and largest run, the median
RMSE and maximum error, the anchored runs and wrong anchor pairings, and the median
run time; ``--markdown`` prints them as a table.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=. python benchmarks/ekf_linearisation.py \\
        --seeds 0 1 2 3 4 5 6 7 --markdown
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time
from typing import Any

from ekf_reference import EKFConfig, run_ekf
from mapfuse.campaign.stats import anees_bounds
from mapfuse.metrics import run_metrics
from mapfuse_core.sim.scenario import Scenario, load_scenario
from mapfuse_core.sim.simulate import simulate

#: Per regime: (scan period in s, steering σ as a multiple of loop600's, steps).
REGIMES: dict[str, tuple[float, float, int]] = {
    "loop600": (0.125, 1.0, 0),
    "rough": (0.5, 5.0, 600),
    "rougher": (0.5, 8.0, 600),
}
LINEARISATIONS = ("measured", "iterated")


def scenario(regime: str) -> Scenario:
    """``loop600`` with the regime's scan period, steering noise and steps."""
    base = load_scenario("loop600")
    dt, scale, steps = REGIMES[regime]
    vehicle = dataclasses.replace(base.vehicle, dt_s=dt, sigma_phi=scale * base.vehicle.sigma_phi)
    return dataclasses.replace(base, vehicle=vehicle, steps=steps or base.steps)


def one_run(regime: str, seed: int) -> list[dict[str, Any]]:
    """Both linearisations, with and without fusion, on one simulated log."""
    log = simulate(scenario(regime), seed=seed, workers=1).log
    rows = []
    for mode in LINEARISATIONS:
        for fusion in (True, False):
            t0 = time.perf_counter()
            res = run_ekf(log, EKFConfig(odometry_linearisation=mode), fusion=fusion)
            wall = time.perf_counter() - t0
            m = run_metrics(res, log).to_json()
            a = m["anchor"]
            rows.append(
                {
                    "regime": regime,
                    "seed": seed,
                    "linearisation": mode,
                    "fusion": fusion,
                    "nees_mean": m["nees"]["mean"],
                    "effective_samples": m["nees"]["mean_interval"]["effective_samples"],
                    "rmse_m": m["position_error_m"]["rmse"],
                    "max_m": m["position_error_m"]["max"],
                    "anchored": a is not None,
                    "wrong_pairings": 0 if a is None else a["pairings"] - a["correct_pairings"],
                    "unconverged_steps": res.details.increment_unconverged,
                    "runtime_s": wall,
                }
            )
    return rows


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """ANEES with its 95 % region, medians and counts over the runs of one group."""
    means = [r["nees_mean"] for r in rows]
    n_eff = sum(r["effective_samples"] or 0.0 for r in rows)
    lo, hi = (float(b) for b in anees_bounds(n_eff))
    return {
        "regime": rows[0]["regime"],
        "linearisation": rows[0]["linearisation"],
        "fusion": rows[0]["fusion"],
        "runs": len(rows),
        "anees": statistics.fmean(means),
        "interval": [lo, hi],
        "run_median": statistics.median(means),
        "run_max": max(means),
        "rmse_median_m": statistics.median(r["rmse_m"] for r in rows),
        "max_median_m": statistics.median(r["max_m"] for r in rows),
        "anchored": sum(r["anchored"] for r in rows),
        "wrong_pairings": sum(r["wrong_pairings"] for r in rows),
        "unconverged_steps": sum(r["unconverged_steps"] for r in rows),
        "runtime_median_s": statistics.median(r["runtime_s"] for r in rows),
    }


def markdown(summaries: list[dict[str, Any]]) -> str:
    """The summaries as one Markdown table."""
    lines = [
        "| regime | linearisation | fusion | ANEES [95 % region] | run's mean NEES: median, "
        "max | RMSE median (m) | max error median (m) | anchored (wrong pairings) "
        "| run time median (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        lo, hi = s["interval"]
        lines.append(
            f"| {s['regime']} | {s['linearisation']} | {'plan' if s['fusion'] else 'none'} "
            f"| {s['anees']:.2f} [{lo:.2f}, {hi:.2f}] | {s['run_median']:.2f}, "
            f"{s['run_max']:.2f} | {s['rmse_median_m']:.3f} | {s['max_median_m']:.3f} "
            f"| {s['anchored']} / {s['runs']} ({s['wrong_pairings']}) "
            f"| {s['runtime_median_s']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--regimes", default=",".join(REGIMES), help="comma list")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    regimes = [r for r in args.regimes.split(",") if r]
    unknown = sorted(set(regimes) - set(REGIMES))
    if unknown:
        ap.error(f"unknown regimes {unknown}; known: {', '.join(REGIMES)}")
    summaries = []
    for regime in regimes:
        rows: list[dict[str, Any]] = []
        for seed in args.seeds:
            for row in one_run(regime, seed):
                print(json.dumps(row), flush=True)
                rows.append(row)
        for mode in LINEARISATIONS:
            for fusion in (True, False):
                group = [r for r in rows if r["linearisation"] == mode and r["fusion"] == fusion]
                s = summarise(group)
                print(json.dumps({"summary": s}), flush=True)
                summaries.append(s)
    if args.markdown:
        print(markdown(summaries))


if __name__ == "__main__":
    main()
