"""The EKF against a causal smoother on the same decisions, on CARMEN logs (prints JSON).

On every log and seed, the EKF runs with the plan (``--fusion none``: without it), and
iSAM2 without a robust kernel takes the EKF's decisions (its association and match).
Both are compared by their *filtered* estimates, the pose of each step from the
measurements up to that step, so the two see the same information at every step: what
the EKF's pose NEES has in excess of iSAM2's is the filter's own (its linearisation),
not its inputs'.

Variants (``--variants``):

* ``extracted``: the log as loaded, every observation as extracted.
* ``redrawn``: only the observations with a reference label (on a plan wall at the
  reference pose), each redrawn from that wall at the reference pose with its own stated
  covariance (``cause_separation._redrawn_line``): the observation model is then exactly
  true.

``--odometry-scale`` scales every term of the simulated odometry's noise model
(:class:`~mapfuse_core.data.datasets.IncrementNoise`), the noise drawn and the
covariance stated alike; ``--ekf`` overrides the EKF's options (JSON), e.g. the bound
on a local map.

One JSON line per (log, seed, variant), then one summary line per (log, variant) with
the ANEES of each estimator over the seeds (the mean of the runs' mean NEES) and the
median run's; ``--markdown`` prints the summary as a table.

    OPENBLAS_NUM_THREADS=1 PYTHONPATH=. python benchmarks/carmen_filter.py \\
        --logs seattle --seeds 0 1 --variants extracted,redrawn --markdown
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

import numpy as np

from benchmarks.carmen_frontend import add_log_arguments, resolve_logs
from benchmarks.cause_separation import _redrawn_line, with_observations
from mapfuse.runner import run, truth_in_global
from mapfuse_core.data.datasets import (
    CarmenOptions,
    IncrementNoise,
    build_floor_plan,
    label_with_plan,
    load_carmen,
)
from mapfuse_core.data.datasets.floorplan import express_line_in
from mapfuse_core.estimate import PoseTrack
from mapfuse_core.evaluation import nees_series, pose_errors
from mapfuse_core.measlog import MeasurementLog

VARIANTS = ("extracted", "redrawn")


def scaled_noise(scale: float) -> IncrementNoise:
    """The default odometry noise model with every term times ``scale``."""
    d = IncrementNoise()
    return IncrementNoise(**{f.name: scale * getattr(d, f.name) for f in dataclasses.fields(d)})


def labelled_only(log: MeasurementLog) -> MeasurementLog:
    """``log`` with the observations that have a reference label only."""
    return with_observations(log, log.feat_true_id >= 0)


def redrawn_from_plan(log: MeasurementLog, walls: Any, seed: int) -> MeasurementLog:
    """``log``'s labelled line observations, each redrawn from its plan wall (in
    ``walls``, the plan's :class:`KnownMapArrays`) at the reference pose with its own
    stated covariance; the unlabelled ones are left out."""
    out = labelled_only(log)
    assert out.true_poses is not None
    rng = np.random.default_rng(np.random.SeedSequence([seed, 11]))
    params = np.array(out.feat_params, copy=True)
    covs = np.array(out.feat_cov, copy=True)
    for j in range(out.n_features):
        pose = out.true_poses[int(out.feat_step[j])]
        truth = express_line_in(pose, walls.params[int(out.feat_true_id[j])])[0]
        params[j], covs[j] = _redrawn_line(truth, out.feat_params[j], out.feat_cov[j], rng)
    # Each draw errs by its covariance alone, independently of the others.
    return dataclasses.replace(out, feat_params=params, feat_cov=covs, feat_gate_cov=None)


def track_nees(track: PoseTrack, truth: np.ndarray) -> tuple[float, float]:
    """Mean 3-dof NEES and position RMSE (m) of ``track`` against ``truth``."""
    err = pose_errors(track.poses, truth[: len(track.poses)])
    nees = nees_series(err.dx, track.covs)
    return float(np.nanmean(nees)), float(np.sqrt(np.mean(np.square(err.position))))


def in_plan_frame(
    filtered: PoseTrack, details: Any, reference: np.ndarray, truth: np.ndarray
) -> dict[str, Any]:
    """The EKF's mean NEES and RMSE over the steps it has an anchor, in the plan's frame
    (``EKFDetails.poses_in_known`` against the reference poses: the plan is built in
    their frame) and in ``Wglobal`` on the same steps; NaN without an anchor.  After it
    fuses, the EKF's pose in ``Wglobal`` carries the anchor's error, which it cannot
    revise once the past poses are marginalised; in the plan's frame it does not."""
    ok = ~np.isnan(details.poses_in_known[:, 0])
    if not ok.any():
        nan = float("nan")
        return {
            "anchored_steps": 0,
            "ekf_plan_frame_nees": nan,
            "ekf_plan_frame_rmse_m": nan,
            "ekf_global_same_steps_nees": nan,
        }
    in_plan = PoseTrack(details.poses_in_known[ok], details.covs_in_known[ok])
    nees, rmse = track_nees(in_plan, reference[: ok.size][ok])
    in_global = PoseTrack(filtered.poses[ok], filtered.covs[ok])
    return {
        "anchored_steps": int(ok.sum()),
        "ekf_plan_frame_nees": nees,
        "ekf_plan_frame_rmse_m": rmse,
        "ekf_global_same_steps_nees": track_nees(in_global, truth[: ok.size][ok])[0],
    }


def one_run(log: MeasurementLog, fusion: bool, ekf_options: dict[str, Any]) -> dict[str, Any]:
    """The EKF and iSAM2 (no kernel) on its decisions, their filtered estimates judged."""
    assert log.true_poses is not None
    truth = truth_in_global(log.true_poses)
    t0 = time.process_time()
    ekf = run(log, "ekf", fusion=fusion, **ekf_options)
    t_ekf = time.process_time() - t0
    isam = run(log, "isam2", fusion=fusion, upstream=ekf.result, graph={"robust": None})
    assert ekf.result.filtered is not None
    assert isam.result.filtered is not None
    e_nees, e_rmse = track_nees(ekf.result.filtered, truth)
    i_nees, i_rmse = track_nees(isam.result.filtered, truth)
    details = ekf.result.details
    return {
        **in_plan_frame(ekf.result.filtered, details, log.true_poses, truth),
        "anchored": ekf.result.anchor is not None,
        "joins": details.joins,
        "ekf_nees": e_nees,
        "ekf_rmse_m": e_rmse,
        "ekf_runtime_s": t_ekf,
        "isam2_filtered_nees": i_nees,
        "isam2_filtered_rmse_m": i_rmse,
    }


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """ANEES (mean of the runs' means) and the median run of each estimator."""
    out: dict[str, Any] = {k: rows[0][k] for k in ("log", "variant")}
    out["runs"] = len(rows)
    out["anchored"] = sum(1 for r in rows if r["anchored"])
    for est in ("ekf", "isam2_filtered"):
        vals = [r[f"{est}_nees"] for r in rows]
        out[f"{est}_anees"] = statistics.fmean(vals)
        out[f"{est}_median"] = statistics.median(vals)
        out[f"{est}_rmse_median_m"] = statistics.median(r[f"{est}_rmse_m"] for r in rows)
    anchored = [r for r in rows if r["anchored_steps"]]
    for key in ("ekf_plan_frame_nees", "ekf_global_same_steps_nees"):
        vals = [r[key] for r in anchored]
        out[key.replace("_nees", "_anees")] = statistics.fmean(vals) if vals else math.nan
        out[key.replace("_nees", "_median")] = statistics.median(vals) if vals else math.nan
    out["ekf_plan_frame_rmse_median_m"] = (
        statistics.median(r["ekf_plan_frame_rmse_m"] for r in anchored) if anchored else math.nan
    )
    return out


def markdown(summaries: list[dict[str, Any]]) -> str:
    """The summaries as a table."""
    lines = [
        "| log | variant | runs (anchored) | EKF: ANEES (median run), RMSE median (m) "
        "| iSAM2 filtered on its decisions: ANEES (median run), RMSE median (m) "
        "| EKF once anchored, in the plan's frame: ANEES (median run), RMSE median (m) "
        "| EKF once anchored, in Wglobal: ANEES (median run) |",
        "|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        lines.append(
            f"| {s['log']} | {s['variant']} | {s['runs']} ({s['anchored']}) "
            f"| {s['ekf_anees']:.1f} ({s['ekf_median']:.1f}), {s['ekf_rmse_median_m']:.2f} "
            f"| {s['isam2_filtered_anees']:.1f} ({s['isam2_filtered_median']:.1f}), "
            f"{s['isam2_filtered_rmse_median_m']:.2f} "
            f"| {s['ekf_plan_frame_anees']:.1f} ({s['ekf_plan_frame_median']:.1f}), "
            f"{s['ekf_plan_frame_rmse_median_m']:.2f} "
            f"| {s['ekf_global_same_steps_anees']:.1f} ({s['ekf_global_same_steps_median']:.1f}) |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_log_arguments(ap)
    ap.add_argument("--variants", default=",".join(VARIANTS), help="comma list")
    ap.add_argument("--fusion", choices=("plan", "none"), default="plan")
    ap.add_argument("--odometry-scale", type=float, default=1.0)
    ap.add_argument("--ekf", type=json.loads, default={}, help="JSON overrides of the EKF")
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    variants = [v for v in args.variants.split(",") if v]
    unknown = sorted(set(variants) - set(VARIANTS))
    if unknown:
        ap.error(f"unknown variants {unknown}; known: {', '.join(VARIANTS)}")
    noise = scaled_noise(args.odometry_scale)
    summaries = []
    for path in resolve_logs(args.data, args.logs):
        name = Path(path).name.split("-corrected")[0]
        rows: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
        plan = None
        for seed in args.seeds:
            full = load_carmen(path, options=CarmenOptions(seed=seed, odometry_noise=noise))
            plan = build_floor_plan(full) if plan is None else plan
            log = label_with_plan(full, plan)
            for v in variants:
                use = log if v == "extracted" else redrawn_from_plan(log, plan.walls, seed)
                row = {"log": name, "seed": seed, "variant": v}
                row.update(one_run(use, args.fusion == "plan", args.ekf))
                print(json.dumps(row), flush=True)
                rows[v].append(row)
        for v in variants:
            s = summarise(rows[v])
            print(json.dumps({"summary": s}), flush=True)
            summaries.append(s)
    if args.markdown:
        print(markdown(summaries))


if __name__ == "__main__":
    main()
