"""Wall time and accuracy of the GTSAM mirror (batch LM and iSAM2) on a log (prints JSON).

Targets (issue 4) on loop600 (2,400 poses), 2-core project machine:
iSAM2 with fusion ≤ 15 s total and ≤ 125 ms per step (p99); batch ≤ 20 s; our
custom line/circle factors ≤ 3× the time of a same-size graph of GTSAM built-in
factors (``BearingRangeFactor2D`` + ``BetweenFactorPose2``) under the same solvers.

The built-in graph has the same poses, odometry factors, prior, landmarks and one
observation factor per logged observation (a bearing–range to a Point2 at the
landmark's position: the centre of a circle, the foot of the first observation
on a line); its measurements are generated from the custom solution with noise,
so both graphs need similar iterations from the same dead-reckoning start.

Usage::

    python benchmarks/bench_graph.py                   # simulate loop600, seed 0
    python benchmarks/bench_graph.py --log out/loop600/log.npz --association truth
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from typing import Any

import gtsam
import numpy as np

from mapfuse_core.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog, load_log
from mapfuse_core.se2 import compose, wrap_angle
from mapfuse_graph.factors import pose_of
from mapfuse_graph.graph import odometry_noise_cov, pose_key
from mapfuse_graph.solvers import (
    GraphResult,
    ISAM2Options,
    graph_metrics,
    levenberg_marquardt,
    run_graph,
)

TARGETS = {"isam2_total_s": 15.0, "isam2_p99_ms": 125.0, "batch_total_s": 20.0, "ratio": 3.0}


def _load(args: argparse.Namespace) -> MeasurementLog:
    if args.log:
        return load_log(args.log)
    from mapfuse_core.scenario import load_scenario
    from mapfuse_core.simulate import simulate

    return simulate(load_scenario(args.scenario), seed=args.seed).log


def _summary(res: GraphResult, log: MeasurementLog) -> dict[str, Any]:
    m = graph_metrics(res, log)
    out: dict[str, Any] = {
        "total_s": round(res.total_time_s, 3),
        "total_cpu_s": round(res.total_cpu_s, 3),
        "build_s": round(res.build_time_s, 3),
        "solve_s": round(res.solve_time_s, 3),
        "marginals_s": round(res.marginals_time_s, 3),
        "factors": res.n_factors,
        "variables": res.n_variables,
        "final_error": round(res.final_error, 3),
        "landmarks": len(res.landmarks.kinds),
        "position_rmse_m": m["position_error_m"] and round(m["position_error_m"]["rmse"], 4),
        "position_max_m": m["position_error_m"] and round(m["position_error_m"]["max"], 4),
        "nees_mean": m["nees"] and round(m["nees"]["mean"], 3),
        "nees_within": m["nees"] and round(m["nees"]["fraction_within_chi2_95"], 4),
        "anchor": m["anchor"],
    }
    if res.backend == "isam2":
        t = res.step_time_s
        out["steps_s"] = round(float(np.sum(t)), 3)
        out["per_step_p50_ms"] = round(1e3 * float(np.percentile(t, 50)), 2)
        out["per_step_p99_ms"] = round(1e3 * float(np.percentile(t, 99)), 2)
        out["per_step_max_ms"] = round(1e3 * float(np.max(t)), 2)
        out.update(res.extra)
        fm = graph_metrics(res, log, "filtered")
        if fm["position_error_m"] is not None:
            out["filtered_position_rmse_m"] = round(fm["position_error_m"]["rmse"], 4)
            out["filtered_nees_mean"] = round(fm["nees"]["mean"], 3)
    if res.lm is not None:
        out["lm_iterations"] = res.lm.iterations
        out["lm_converged"] = res.lm.converged
    return out


def _agreement(a: GraphResult, b: GraphResult) -> dict[str, float]:
    d = a.poses - b.poses
    d[:, 2] = wrap_angle(d[:, 2])
    sig = np.sqrt(np.einsum("kii->ki", b.covs))
    rel = np.abs(d[1:]) / sig[1:]
    return {
        "max_abs_xy_m": float(np.abs(d[:, :2]).max()),
        "max_abs_theta_rad": float(np.abs(d[:, 2]).max()),
        "max_over_sigma": float(rel.max()),
    }


# --------------------------------------------------------------------------- built-in twin


def _builtin_twin(
    log: MeasurementLog, res: GraphResult, rng: np.random.Generator
) -> tuple[list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]], int]:
    """Per-step (factors, new values) of the same-size graph of built-in factors."""
    n = res.poses.shape[0]
    lm_pos: dict[int, np.ndarray] = {}
    for i in range(len(res.landmarks.kinds)):
        lm_pos[i] = res.landmarks.params[i, :2].copy()
    noise_br = gtsam.noiseModel.Diagonal.Sigmas(np.array([math.pi / 720, 0.05]))
    prior = gtsam.noiseModel.Diagonal.Sigmas(np.array([1e-6, 1e-6, 1e-6]))
    steps: list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]] = []
    est = np.zeros(3)
    seen: set[int] = set()
    n_obs = 0
    for k in range(n):
        g, v = gtsam.NonlinearFactorGraph(), gtsam.Values()
        if k == 0:
            g.add(gtsam.PriorFactorPose2(pose_key(0), gtsam.Pose2(), prior))
        else:
            u = log.odometry[k]
            est = compose(est, u)
            noise = gtsam.noiseModel.Gaussian.Covariance(odometry_noise_cov(u, log.odometry_cov[k]))
            g.add(gtsam.BetweenFactorPose2(pose_key(k - 1), pose_key(k), gtsam.Pose2(*u), noise))
        v.insert(pose_key(k), gtsam.Pose2(*est))
        sl = log.feature_slice(k)
        x = res.poses[k]
        for j in range(sl.start, sl.stop):
            i = int(res.obs_landmark[j])
            if i < 0:
                continue
            p = lm_pos[i]
            dx, dy = p[0] - x[0], p[1] - x[1]
            bearing = float(wrap_angle(math.atan2(dy, dx) - x[2])) + rng.normal(0, math.pi / 720)
            rng_m = math.hypot(dx, dy) + rng.normal(0, 0.05)
            key = int(gtsam.symbol("p", i))
            g.add(
                gtsam.BearingRangeFactor2D(pose_key(k), key, gtsam.Rot2(bearing), rng_m, noise_br)
            )
            if i not in seen:
                seen.add(i)
                c, s = math.cos(est[2] + bearing), math.sin(est[2] + bearing)
                v.insert(key, np.array([est[0] + rng_m * c, est[1] + rng_m * s]))
            n_obs += 1
        steps.append((g, v))
    return steps, n_obs


def _builtin_runs(
    steps: list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]], isam2: ISAM2Options
) -> dict[str, Any]:
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for g, v in steps:
        graph.push_back(g)
        values.insert(v)
    t0 = time.perf_counter()
    sol, report = levenberg_marquardt(graph, values)
    batch_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    m = gtsam.Marginals(graph.linearize(sol), sol)
    for k in range(len(steps)):
        m.marginalCovariance(pose_key(k))
    marg_s = time.perf_counter() - t0

    params = gtsam.ISAM2Params()
    th = isam2.relinearize_threshold
    if isinstance(th, dict):
        tmap = gtsam.ISAM2ThresholdMap()
        tmap.insert(("x", np.asarray(th["x"], dtype=float)))
        tmap.insert(("p", np.asarray(th["l"][:1] * 2, dtype=float)))
        params.setRelinearizeThreshold(tmap)
    else:
        params.setRelinearizeThreshold(float(th))
    params.relinearizeSkip = isam2.relinearize_skip
    isam = gtsam.ISAM2(params)
    keep = isam.getLinearizationPoint()
    times = np.zeros(len(steps))
    t_all = time.perf_counter()
    for k, (g, v) in enumerate(steps):
        t0 = time.perf_counter()
        isam.update(g, v)
        x = pose_of(isam.calculateEstimatePose2(pose_key(k)))
        isam.marginalCovariance(pose_key(k))
        times[k] = time.perf_counter() - t0
        del x
    for _ in range(isam2.final_updates):
        isam.update()
    isam.calculateBestEstimate()
    isam_s = time.perf_counter() - t_all
    del keep
    return {
        "batch_lm_s": round(batch_s, 3),
        "batch_lm_iterations": report.iterations,
        "batch_marginals_s": round(marg_s, 3),
        "isam2_s": round(isam_s, 3),
        "isam2_per_step_p99_ms": round(1e3 * float(np.percentile(times, 99)), 2),
        "linearize_s": round(_time(lambda: graph.linearize(sol)), 4),
        "error_s": round(_time(lambda: graph.error(sol)), 4),
    }


def _time(f: Any, repeat: int = 3) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        f()
        best = min(best, time.perf_counter() - t0)
    return best


def _custom_costs(log: MeasurementLog, res: GraphResult, association: str) -> dict[str, float]:
    """Per-call cost of our observation factors alone (linearize and error)."""
    from mapfuse_graph.factors import observation_factor
    from mapfuse_graph.graph import landmark_key

    g = gtsam.NonlinearFactorGraph()
    v = gtsam.Values()
    for k in range(res.poses.shape[0]):
        v.insert(pose_key(k), gtsam.Pose2(*res.poses[k]))
    for i, kind in enumerate(res.landmarks.kinds):
        vv = res.landmarks.variables[i]
        v.insert(landmark_key(i, FeatureKind(int(kind))), vv[~np.isnan(vv)])
    counts = {FeatureKind.LINE: 0, FeatureKind.CIRCLE: 0}
    for j in np.nonzero(res.obs_landmark >= 0)[0]:
        kind = FeatureKind(int(log.feat_kind[j]))
        i = int(res.obs_landmark[j])
        g.add(
            observation_factor(
                kind,
                pose_key(int(log.feat_step[j])),
                landmark_key(i, kind),
                log.feat_params[j],
                log.feat_cov[j],
            )
        )
        counts[kind] += 1
    n = max(g.size(), 1)
    lin = _time(lambda: g.linearize(v))
    err = _time(lambda: g.error(v))
    del association
    return {
        "observation_factors": int(g.size()),
        "lines": counts[FeatureKind.LINE],
        "circles": counts[FeatureKind.CIRCLE],
        "linearize_us_per_factor": round(1e6 * lin / n, 2),
        "error_us_per_factor": round(1e6 * err / n, 2),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--log", default=None, help="log.npz to use (default: simulate --scenario)")
    ap.add_argument("--scenario", default="loop600")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--association",
        default="truth",
        choices=["truth", "ekf", "own"],
        help="truth (default), ekf (runs the EKF first), own",
    )
    ap.add_argument("--no-fusion", dest="fusion", action="store_false")
    ap.add_argument("--steps", type=int, default=None, help="only the first STEPS steps")
    ap.add_argument("--skip-builtin", action="store_true", help="skip the built-in comparison")
    args = ap.parse_args()

    t0 = time.perf_counter()
    log = _load(args)
    load_s = time.perf_counter() - t0
    ekf = None
    ekf_s = None
    if args.association == "ekf":
        from ekf_reference import EKFConfig, run_ekf

        t0 = time.perf_counter()
        ekf = run_ekf(log, EKFConfig(fusion=args.fusion))
        ekf_s = round(time.perf_counter() - t0, 3)
    common = {
        "fusion": args.fusion,
        "association": args.association,
        "ekf_result": ekf,
        "steps": args.steps,
    }
    isam_opts = ISAM2Options()
    res_i = run_graph(log, "isam2", isam2=isam_opts, **common)
    res_b = run_graph(log, "batch", init="odometry", **common)
    out: dict[str, Any] = {
        "benchmark": "graph",
        "scenario": log.scenario,
        "seed": log.seed,
        "steps": int(res_b.poses.shape[0]),
        "observations": int(np.sum(res_b.obs_landmark >= 0)),
        "fusion": args.fusion,
        "association": args.association,
        "machine": {"cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2)},
        "load_log_s": round(load_s, 3),
        "ekf_s": ekf_s,
        "targets": TARGETS,
        "isam2": _summary(res_i, log),
        "batch": _summary(res_b, log),
        "isam2_final_vs_batch": _agreement(res_i, res_b),
    }
    out["custom_factor_cost"] = _custom_costs(log, res_b, args.association)
    if not args.skip_builtin:
        steps, n_obs = _builtin_twin(log, res_b, np.random.default_rng(0))
        bi = _builtin_runs(steps, isam_opts)
        bi["observation_factors"] = n_obs
        out["builtin"] = bi
        custom_batch = res_b.solve_time_s
        out["custom_over_builtin"] = {
            "batch_lm": round(custom_batch / max(bi["batch_lm_s"], 1e-9), 2),
            "isam2": round(float(np.sum(res_i.step_time_s)) / max(bi["isam2_s"], 1e-9), 2),
        }
    out["met"] = {
        "isam2_total": res_i.total_time_s <= TARGETS["isam2_total_s"],
        "isam2_p99": 1e3 * float(np.percentile(res_i.step_time_s, 99)) <= TARGETS["isam2_p99_ms"],
        "batch_total": res_b.total_time_s <= TARGETS["batch_total_s"],
    }
    if "custom_over_builtin" in out:
        out["met"]["ratio"] = all(
            v <= TARGETS["ratio"] for v in out["custom_over_builtin"].values()
        )
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
