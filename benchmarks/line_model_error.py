"""Line model-error terms on CARMEN logs: estimated per log against the profile's (prints JSON).

For every corrected log given (``--logs``; default every ``*-corrected.log*`` in
``--data``/carmen):

* **the estimate** (:func:`~mapfuse_core.data.datasets.line_noise.estimate_line_model_error`
  on the log extracted without model-error terms): line observations on plan walls,
  mean whitened squared residual per dof without terms, autocorrelation time τ per
  dof, the σ on ρ and α;
* **what it does to the estimators** with the association taken from the reference
  labels (``association="truth"``) and no known map, so that only the line noise model
  differs: for every seed of the simulated odometry and every ``--estimators`` entry
  (a graph backend with the ``carmen:`` profile's Cauchy kernel, ``NAME+KERNEL`` for
  another, ``NAME+gauss`` for none), the log loaded with the
  profile's terms and with the estimated ones: position RMSE and mean pose NEES.

One JSON line per (log, seed, terms, estimator) and, after every log, a summary line
(ANEES over the seeds with the two-sided 95 % acceptance region from the runs'
effective samples, median RMSE); ``--markdown`` prints the tables at the end.

    OPENBLAS_NUM_THREADS=1 python benchmarks/line_model_error.py --seeds 0 1 2 3 4 5 6 7 \\
        --markdown
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import statistics
import time
from pathlib import Path
from typing import Any

from benchmarks.carmen_frontend import add_log_arguments, backend_and_kernel, resolve_logs
from mapfuse.campaign.stats import anees_bounds
from mapfuse.runner import run
from mapfuse_core.data.datasets import CarmenOptions, build_floor_plan, label_with_plan, load_carmen
from mapfuse_core.data.datasets.line_noise import estimate_line_model_error
from mapfuse_core.perception.extraction import ExtractionParams

SOURCES = ("profile", "independent", "correlated")
"""``CarmenOptions.line_model_error`` values compared."""


def estimate_row(path: Path) -> dict[str, Any]:
    """The estimate on ``path`` extracted without model-error terms, as a JSON row."""
    bare = dataclasses.replace(
        ExtractionParams.indoor_sick(), line_model_sigma_m=0.0, line_model_sigma_rad=0.0
    )
    log = load_carmen(path, options=CarmenOptions(extraction=bare, line_model_error="profile"))
    est = estimate_line_model_error(log)
    ind = estimate_line_model_error(log, correlated=False)
    return {
        "log": _name(path),
        "observations": est.observations,
        "nees_per_dof_without": list(est.nees_without),
        "iact": list(est.iact),
        "sigma_m": est.sigma_m,
        "sigma_deg": math.degrees(est.sigma_rad),
        "independent_sigma_m": ind.sigma_m,
        "independent_sigma_deg": math.degrees(ind.sigma_rad),
    }


def _name(path: Path) -> str:
    return path.name.split("-corrected")[0]


def _runs(path: Path, seeds: list[int], estimators: list[str]) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    plan = None
    for source in SOURCES:
        for seed in seeds:
            opts = CarmenOptions(seed=seed, line_model_error=source)  # type: ignore[arg-type]
            raw = load_carmen(path, options=opts)
            # The plan's walls come from the scatter of their members, not from the
            # observations' covariances: one plan serves both sources.
            plan = build_floor_plan(raw) if plan is None else plan
            log = label_with_plan(raw, plan)
            for est in estimators:
                name, kw = backend_and_kernel(est)
                c0 = time.process_time()
                r = run(log, name, fusion=False, association="truth", **kw)
                m = r.metrics
                # A corrected log has its reference: both metrics exist.
                assert m.nees is not None
                assert m.position_error is not None
                iv = m.nees.mean_interval
                rows.append(
                    {
                        "log": _name(path),
                        "seed": seed,
                        "terms": source,
                        "estimator": est,
                        "rmse_m": m.position_error.rmse,
                        "nees_mean": m.nees.mean,
                        "nees_effective_samples": iv.effective_samples if iv else None,
                        "cpu_s": time.process_time() - c0,
                    }
                )
                print(json.dumps(rows[-1]), flush=True)
    return rows


def summary(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """ANEES over the seeds (mean of the runs' means) with the 95 % acceptance region of
    a consistent estimator from their effective samples summed, per (terms, estimator)."""
    out = []
    keys = sorted(
        {(r["terms"], r["estimator"]) for r in rows}, key=lambda k: (SOURCES.index(k[0]), k[1])
    )
    for terms, est in keys:
        runs = [r for r in rows if r["terms"] == terms and r["estimator"] == est]
        n_eff = sum(r["nees_effective_samples"] or 0.0 for r in runs)
        lo, hi = (float(b) for b in anees_bounds(n_eff))
        out.append(
            {
                "log": runs[0]["log"],
                "terms": terms,
                "estimator": est,
                "seeds": len(runs),
                "anees": statistics.fmean(r["nees_mean"] for r in runs),
                "interval": [lo, hi],
                "rmse_median_m": statistics.median(r["rmse_m"] for r in runs),
            }
        )
    return out


def _markdown(estimates: list[dict[str, Any]], summaries: list[dict[str, Any]]) -> str:
    lines = [
        "| log | observations on plan walls | NEES/dof without terms (lateral, angle) "
        "| τ (lateral, angle) | σ on ρ (m), α (°): independent | correlated |",
        "|---|---|---|---|---|---|",
    ]
    for e in estimates:
        lines.append(
            f"| {e['log']} | {e['observations']} | {e['nees_per_dof_without'][0]:.1f}, "
            f"{e['nees_per_dof_without'][1]:.1f} | {e['iact'][0]:.1f}, {e['iact'][1]:.1f} "
            f"| {e['independent_sigma_m']:.3f}, {e['independent_sigma_deg']:.2f} "
            f"| {e['sigma_m']:.3f}, {e['sigma_deg']:.2f} |"
        )
    lines += [
        "",
        "| log | estimator | terms | ANEES [95 % region] | RMSE median (m) |",
        "|---|---|---|---|---|",
    ]
    for s in summaries:
        lines.append(
            f"| {s['log']} | {s['estimator']} | {s['terms']} | {s['anees']:.1f} "
            f"[{s['interval'][0]:.2f}, {s['interval'][1]:.2f}] | {s['rmse_median_m']:.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_log_arguments(ap)
    ap.add_argument(
        "--estimators",
        default="batch+gauss,batch",
        help="comma list of graph backends (the carmen: profile's Cauchy kernel); "
        "NAME+KERNEL for another kernel, NAME+gauss for none",
    )
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    estimators = [e for e in args.estimators.split(",") if e]
    estimates, summaries = [], []
    for path in resolve_logs(args.data, args.logs):
        row = estimate_row(path)
        estimates.append(row)
        print(json.dumps({"estimate": row}), flush=True)
        for s in summary(_runs(path, args.seeds, estimators)):
            summaries.append(s)
            print(json.dumps({"summary": s}), flush=True)
    if args.markdown:
        print(_markdown(estimates, summaries))


if __name__ == "__main__":
    main()
