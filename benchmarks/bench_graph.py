"""Wall time and accuracy of the GTSAM mirror (batch LM and iSAM2) on a log (prints JSON).

Targets on loop600 (2,400 poses), 2-core project machine:
iSAM2 with fusion ≤ 15 s total and ≤ 125 ms per step (p99); batch ≤ 20 s; our
custom line/circle factors ≤ 3× the time of a same-size graph of GTSAM built-in
factors under the same solvers.

Same-size comparison
--------------------
Both graphs are solved by the *same* code: :func:`levenberg_marquardt` (with the
options ``run_graph`` uses, error from the linearisation) for batch, and one iSAM2
driver (``update``, newest pose's estimate and marginal per step, holding the
linearisation point, the same relinearisation thresholds) for iSAM2, both from the
same dead-reckoning initial values.  The built-in twin is a factor-by-factor
translation of our graph, so it has the same number of factors of each residual
dimension and the same number of variables of each tangent dimension
(``same_size`` in the output checks it):

* Pose2 prior, odometry ``BetweenFactorPose2``, anchor prior: the same factor objects;
* line observation (Pose2, (ρ, α)), 2-dim → ``BearingRangeFactor2D`` (Pose2, Point2);
* circle observation (Pose2, (x, y, r)), 3-dim → ``BetweenFactorPose2`` (Pose2, Pose2);
* known line / circle prior, 2 / 3-dim → ``PriorFactorPoint2`` / ``PriorFactorPose2``;
* line / circle tie (anchor, landmark, known), 2 / 3-dim → ``BetweenFactorPoint2`` /
  ``BetweenFactorPose2`` (landmark, known).

The ties are the one difference: GTSAM's Python wrapper has no three-key 2-D
factor, so the twin's ties leave out the anchor (43 of 15k factors on loop600).
Each translated factor keeps our factor's noise model; its measurement comes from
our batch solution (built-in measurement functions, plus noise drawn from that
noise model for the observations), so both graphs need similar iterations.  They
still may differ by one, so the batch ratio is also given per linearisation (one
candidate step: linearise, damp, eliminate, retract).

Ratios are reported on CPU time (``time.process_time``; GTSAM here is
single-threaded, so on an idle machine CPU ≈ wall) and on wall time; the targets
are judged on CPU time because other jobs on a shared machine inflate wall time
unevenly.  Batch timings are the best of ``--repeat`` interleaved runs.

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

from mapfuse.metrics import run_metrics
from mapfuse_core.estimate import AssociationDecisions, EstimatorResult
from mapfuse_core.geometry.se2 import wrap_angle
from mapfuse_core.measlog import MeasurementLog, load_log
from mapfuse_graph.factors import pose_of
from mapfuse_graph.graph import GraphBuilder, GraphOptions, pose_key
from mapfuse_graph.options import AssociationName
from mapfuse_graph.solvers import (
    ISAM2Options,
    _ValuesEstimate,  # the batch solver's own view of its growing Values
    levenberg_marquardt,
    run_graph,
)

TARGETS = {"isam2_total_s": 15.0, "isam2_p99_ms": 125.0, "batch_total_s": 20.0, "ratio": 3.0}

Steps = list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]]


def _load(args: argparse.Namespace) -> MeasurementLog:
    if args.log:
        return load_log(args.log)
    from mapfuse_core.sim.scenario import load_scenario
    from mapfuse_core.sim.simulate import simulate

    return simulate(load_scenario(args.scenario), seed=args.seed).log


def _summary(res: EstimatorResult, log: MeasurementLog) -> dict[str, Any]:
    m = run_metrics(res, log).to_json()
    d = res.details
    out: dict[str, Any] = {
        "total_s": round(d.total_time_s, 3),
        "total_cpu_s": round(d.total_cpu_s, 3),
        "build_s": round(d.build_time_s, 3),
        "solve_s": round(d.solve_time_s, 3),
        "marginals_s": round(d.marginals_time_s, 3),
        "factors": d.n_factors,
        "variables": d.n_variables,
        "final_error": round(d.final_error, 3),
        "landmarks": len(res.map.kinds),
        "position_rmse_m": m["position_error_m"] and round(m["position_error_m"]["rmse"], 4),
        "position_max_m": m["position_error_m"] and round(m["position_error_m"]["max"], 4),
        "nees_mean": m["nees"] and round(m["nees"]["mean"], 3),
        "nees_within": m["nees"] and round(m["nees"]["fraction_within_chi2_95"], 4),
        "anchor": m["anchor"],
    }
    if res.estimator == "isam2":
        t = res.step_time_s
        out["steps_s"] = round(float(np.sum(t)), 3)
        out["per_step_p50_ms"] = round(1e3 * float(np.percentile(t, 50)), 2)
        out["per_step_p99_ms"] = round(1e3 * float(np.percentile(t, 99)), 2)
        if d.step_cpu_s is not None:
            out["per_step_cpu_p99_ms"] = round(1e3 * float(np.percentile(d.step_cpu_s, 99)), 2)
        out["per_step_max_ms"] = round(1e3 * float(np.max(t)), 2)
        out.update(d.extra)
        fm = run_metrics(res, log, "filtered").to_json()
        if fm["position_error_m"] is not None:
            out["filtered_position_rmse_m"] = round(fm["position_error_m"]["rmse"], 4)
            out["filtered_nees_mean"] = round(fm["nees"]["mean"], 3)
    if d.lm is not None:
        out["lm_iterations"] = d.lm.iterations
        out["lm_converged"] = d.lm.converged
    return out


def _agreement(a: EstimatorResult, b: EstimatorResult) -> dict[str, float]:
    d = a.poses - b.poses
    d[:, 2] = wrap_angle(d[:, 2])
    sig = np.sqrt(np.einsum("kii->ki", b.covs))
    rel = np.abs(d[1:]) / sig[1:]
    return {
        "max_abs_xy_m": float(np.abs(d[:, :2]).max()),
        "max_abs_theta_rad": float(np.abs(d[:, 2]).max()),
        "max_over_sigma": float(rel.max()),
    }


# --------------------------------------------------------------------------- same-size comparison


def _custom_steps(
    log: MeasurementLog, args: argparse.Namespace, ekf: Any, res_b: EstimatorResult
) -> Steps:
    """Our per-step (factors, initial values), built exactly as the batch backend builds them."""
    association: AssociationName = "truth"
    decisions: AssociationDecisions | None = None
    if args.association == "own":
        # run_graph decided these in an iSAM2 pre-pass; reuse its decisions.
        assert res_b.decisions is not None
        association, decisions = "given", AssociationDecisions(*res_b.decisions.arrays)
    elif args.association == "ekf":
        association, decisions = "given", ekf.decisions
    builder = GraphBuilder(
        log,
        GraphOptions(),
        fusion=args.fusion,
        association=association,
        decisions=decisions,
        steps=args.steps,
    )
    grown = gtsam.Values()
    est = _ValuesEstimate(grown)
    steps: Steps = []
    for k in range(builder.n_steps):
        sg = builder.step(k, est)
        grown.insert(sg.values)
        steps.append((sg.factors, sg.values))
    return steps


def _union(steps: Steps) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values]:
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    for g, v in steps:
        graph.push_back(g)
        values.insert(v)
    return graph, values


def _chr(key: int) -> str:
    return chr(gtsam.Symbol(key).chr())


def _draw(noise: gtsam.noiseModel.Base, rng: np.random.Generator) -> np.ndarray:
    """A sample of ``noise`` (Gaussian models only; zero for anything else)."""
    cov = np.asarray(noise.covariance()) if hasattr(noise, "covariance") else None
    if cov is None:
        return np.zeros(noise.dim())
    out: np.ndarray = np.linalg.cholesky(cov) @ rng.standard_normal(cov.shape[0])
    return out


def _twin_truth(values: gtsam.Values, steps: Steps) -> dict[int, Any]:
    """Values the twin's measurements are made from: Pose2 / Point2 per key, from ``values``.

    A line ``(ρ, α)`` becomes the foot on it of the first pose that observes it (a point
    at sensor range); a known line the foot of its normal; circles and known circles a
    Pose2 at their centre.
    """
    truth: dict[int, Any] = {}
    for g, _ in steps:
        for i in range(g.size()):
            keys = list(g.at(i).keys())
            for key in keys:
                if key in truth:
                    continue
                ch = _chr(key)
                if ch in "xa":
                    truth[key] = values.atPose2(key)
                elif ch in "cq":
                    c = np.asarray(values.atVector(key))
                    truth[key] = gtsam.Pose2(float(c[0]), float(c[1]), 0.0)
                elif ch == "k":
                    rho, alpha = np.asarray(values.atVector(key)).tolist()
                    truth[key] = rho * np.array([math.cos(alpha), math.sin(alpha)])
                elif ch == "l" and _chr(keys[0]) == "x":  # an observation, not a tie
                    rho, alpha = np.asarray(values.atVector(key)).tolist()
                    n = np.array([math.cos(alpha), math.sin(alpha)])
                    x = values.atPose2(keys[0]).translation()
                    truth[key] = x + (rho - float(x @ n)) * n
    return truth


def _builtin_twin(steps: Steps, values: gtsam.Values, rng: np.random.Generator) -> Steps:
    """Per-step built-in translation of our graph (table in the module docstring)."""
    truth = _twin_truth(values, steps)
    out: Steps = []
    for g, v in steps:
        tg, tv = gtsam.NonlinearFactorGraph(), gtsam.Values()
        new_keys = list(v.keys())
        for key in new_keys:
            ch = _chr(key)
            if ch in "xa":
                tv.insert(key, v.atPose2(key))  # same dead-reckoning start as ours
            elif ch in "kq":
                tv.insert(key, truth[key])  # at their prior mean, like ours
        for i in range(g.size()):
            f = g.at(i)
            keys = list(f.keys())
            chars = "".join(_chr(k) for k in keys)
            if not isinstance(f, gtsam.CustomFactor) and chars in ("x", "a", "xx"):
                tg.add(f)
                continue
            # g.at() hands back the derived factor: every one here has a noise model.
            noise = f.noiseModel()  # type: ignore[attr-defined]
            if chars == "k":
                tg.add(gtsam.PriorFactorPoint2(keys[0], truth[keys[0]], noise))
            elif chars == "q":
                tg.add(gtsam.PriorFactorPose2(keys[0], truth[keys[0]], noise))
            elif chars == "xl":
                X, P = truth[keys[0]], truth[keys[1]]
                e = _draw(noise, rng)
                b = X.bearing(P).theta() + e[0]
                r = X.range(P) + e[1]
                tg.add(gtsam.BearingRangeFactor2D(keys[0], keys[1], gtsam.Rot2(b), r, noise))
                if v.exists(keys[1]) and not tv.exists(keys[1]):
                    x0 = v.atPose2(keys[0])
                    tv.insert(keys[1], x0.transformFrom(r * np.array([math.cos(b), math.sin(b)])))
            elif chars == "xc":
                X, C = truth[keys[0]], truth[keys[1]]
                m = X.between(C).retract(_draw(noise, rng))
                tg.add(gtsam.BetweenFactorPose2(keys[0], keys[1], m, noise))
                if v.exists(keys[1]) and not tv.exists(keys[1]):
                    tv.insert(keys[1], v.atPose2(keys[0]).compose(m))
            elif chars == "alk":
                L, K = truth[keys[1]], truth[keys[2]]
                tg.add(gtsam.BetweenFactorPoint2(keys[1], keys[2], K - L, noise))
            elif chars == "acq":
                L, K = truth[keys[1]], truth[keys[2]]
                tg.add(gtsam.BetweenFactorPose2(keys[1], keys[2], L.between(K), noise))
            else:
                raise ValueError(f"no built-in twin for a factor on keys {chars!r}")
        out.append((tg, tv))
    return out


def _size(graph: gtsam.NonlinearFactorGraph, values: gtsam.Values) -> dict[str, Any]:
    fdims: dict[int, int] = {}
    for i in range(graph.size()):
        d = int(graph.at(i).dim())
        fdims[d] = fdims.get(d, 0) + 1
    vdims: dict[int, int] = {}
    zero = values.zeroVectors()
    keys = list(values.keys())
    for key in keys:
        d = int(zero.at(key).shape[0])
        vdims[d] = vdims.get(d, 0) + 1
    return {
        "factors": int(graph.size()),
        "factors_by_dim": {str(k): fdims[k] for k in sorted(fdims)},
        "variables": int(values.size()),
        "variables_by_dim": {str(k): vdims[k] for k in sorted(vdims)},
    }


class _Counted:
    """A graph that counts the linearisations LM asks of it (each is one candidate step)."""

    def __init__(self, graph: gtsam.NonlinearFactorGraph) -> None:
        self.graph = graph
        self.linearizations = 0

    def linearize(self, values: gtsam.Values) -> gtsam.GaussianFactorGraph:
        self.linearizations += 1
        return self.graph.linearize(values)

    def error(self, values: gtsam.Values) -> float:
        return float(self.graph.error(values))


def _lm_once(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
) -> tuple[gtsam.Values, Any, int, float, float]:
    """The batch backend's LM on ``graph``: solution, report, linearisations, CPU and wall s."""
    counted = _Counted(graph)
    w0, c0 = time.perf_counter(), time.process_time()
    sol, report = levenberg_marquardt(counted, values, error_from_linearization=True)  # type: ignore[arg-type]
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    return sol, report, counted.linearizations, cpu, wall


def _time_lm_pair(
    graphs: list[tuple[gtsam.NonlinearFactorGraph, gtsam.Values]], repeat: int
) -> list[dict[str, Any]]:
    """Best-of-``repeat`` wall and CPU time of LM on each graph, runs interleaved.

    Interleaving gives both graphs the same share of whatever else the machine is
    doing.  Also per linearisation (one linearise + damp + eliminate + retract): the
    graphs may need a different number of iterations to meet the same tolerance.
    """
    best = [[math.inf, math.inf] for _ in graphs]
    last: list[Any] = [None] * len(graphs)
    for _ in range(repeat):
        for i, (g, v) in enumerate(graphs):
            _, report, n, cpu, wall = _lm_once(g, v)
            best[i] = [min(best[i][0], cpu), min(best[i][1], wall)]
            last[i] = (report, n)
    out = []
    for (cpu, wall), (report, n) in zip(best, last, strict=True):
        out.append(
            {
                "cpu_s": round(cpu, 3),
                "wall_s": round(wall, 3),
                "iterations": report.iterations,
                "linearizations": n,
                "cpu_ms_per_linearization": round(1e3 * cpu / n, 2),
                "final_error": round(report.final_error, 3),
            }
        )
    return out


def _threshold_map(th: dict[str, tuple[float, ...]], twin: bool) -> gtsam.ISAM2ThresholdMap:
    tmap = gtsam.ISAM2ThresholdMap()
    for ch, v in th.items():
        vals = tuple(v)
        if twin and ch in "lk":
            # The twin's line landmarks are Point2 (m, m), ours (ρ, α) (m, rad).
            vals = (vals[0], vals[0])
        tmap.insert((ch, np.asarray(vals, dtype=float)))
    return tmap


def _time_isam2(steps: Steps, isam2: ISAM2Options, twin: bool) -> dict[str, Any]:
    """The iSAM2 backend's per-step work on prebuilt steps (wall and CPU)."""
    params = gtsam.ISAM2Params()
    th = isam2.relinearize_threshold
    if isinstance(th, dict):
        params.setRelinearizeThreshold(_threshold_map(th, twin))
    else:
        params.setRelinearizeThreshold(float(th))
    params.relinearizeSkip = isam2.relinearize_skip
    params.setFactorization(isam2.factorization)
    isam = gtsam.ISAM2(params)
    keep = isam.getLinearizationPoint()  # callbacks get this object, not a copy
    times = np.zeros(len(steps))
    relin = 0
    w_all, c_all = time.perf_counter(), time.process_time()
    for k, (g, v) in enumerate(steps):
        t0 = time.perf_counter()
        relin += int(isam.update(g, v).getVariablesRelinearized())
        pose_of(isam.calculateEstimatePose2(pose_key(k)))
        isam.marginalCovariance(pose_key(k))
        times[k] = time.perf_counter() - t0
    final = gtsam.ISAM2UpdateParams()
    final.force_relinearize = True  # as the backend's final updates
    for _ in range(isam2.final_updates):
        isam.update(gtsam.NonlinearFactorGraph(), gtsam.Values(), final)
    isam.calculateBestEstimate()
    cpu = time.process_time() - c_all
    wall = time.perf_counter() - w_all
    del keep
    return {
        "cpu_s": round(cpu, 3),
        "wall_s": round(wall, 3),
        "per_step_p99_ms": round(1e3 * float(np.percentile(times, 99)), 2),
        "variables_relinearized": relin,
    }


def _time(f: Any, repeat: int = 3) -> float:
    best = math.inf
    for _ in range(repeat):
        t0 = time.process_time()
        f()
        best = min(best, time.process_time() - t0)
    return best


def _observation_costs(
    graph: gtsam.NonlinearFactorGraph, values: gtsam.Values
) -> dict[str, float | int]:
    """CPU µs per linearize / error call of the observation factors (pose–landmark) alone."""
    obs = gtsam.NonlinearFactorGraph()
    for i in range(graph.size()):
        f = graph.at(i)
        keys = list(f.keys())
        if len(keys) == 2 and _chr(keys[0]) == "x" and _chr(keys[1]) in "lc":
            obs.add(f)
    n = max(obs.size(), 1)
    return {
        "observation_factors": int(obs.size()),
        "linearize_us_per_factor": round(1e6 * _time(lambda: obs.linearize(values)) / n, 2),
        "error_us_per_factor": round(1e6 * _time(lambda: obs.error(values)) / n, 2),
    }


def _ratio(a: float, b: float) -> float:
    return round(a / max(b, 1e-9), 2)


def _same_size_comparison(
    log: MeasurementLog,
    args: argparse.Namespace,
    ekf: Any,
    res_b: EstimatorResult,
    isam2: ISAM2Options,
) -> dict[str, Any]:
    ours = _custom_steps(log, args, ekf, res_b)
    g_o, v_o = _union(ours)
    sol_o = _lm_once(g_o, v_o)[0]  # the twin's measurements are made from it
    twin = _builtin_twin(ours, sol_o, np.random.default_rng(0))
    g_t, v_t = _union(twin)
    sol_t = _lm_once(g_t, v_t)[0]
    lm_o, lm_t = _time_lm_pair([(g_o, v_o), (g_t, v_t)], args.repeat)
    size_o, size_t = _size(g_o, v_o), _size(g_t, v_t)
    out: dict[str, Any] = {
        "same_size": size_o == size_t,
        "custom": {
            **size_o,
            "batch_lm": lm_o,
            "observation_cost": _observation_costs(g_o, sol_o),
        },
        "builtin": {
            **size_t,
            "batch_lm": lm_t,
            "observation_cost": _observation_costs(g_t, sol_t),
        },
    }
    if not args.skip_isam2_ratio:
        out["custom"]["isam2"] = _time_isam2(ours, isam2, twin=False)
        out["builtin"]["isam2"] = _time_isam2(twin, isam2, twin=True)
    return out


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
    ap.add_argument(
        "--skip-isam2-ratio", action="store_true", help="compare batch LM only (faster)"
    )
    ap.add_argument("--repeat", type=int, default=5, help="batch LM timings: best of REPEAT")
    args = ap.parse_args()
    if args.repeat < 1:
        ap.error("--repeat must be >= 1")

    t0 = time.perf_counter()
    log = _load(args)
    load_s = time.perf_counter() - t0
    ekf = None
    ekf_s = None
    if args.association == "ekf":
        from ekf_reference import EKFConfig, run_ekf

        t0 = time.perf_counter()
        ekf = run_ekf(log, EKFConfig(), fusion=args.fusion)
        ekf_s = round(time.perf_counter() - t0, 3)
    common = {
        "fusion": args.fusion,
        # The EKF's decisions are given to the graph as they stand.
        "association": "given" if ekf is not None else args.association,
        "decisions": None if ekf is None else ekf.decisions,
        "steps": args.steps,
    }
    isam_opts = ISAM2Options()
    res_i = run_graph(log, "isam2", isam2=isam_opts, **common)
    # Batch starts from dead reckoning here (init="odometry"): no EKF poses needed.
    res_b = run_graph(log, "batch", init="odometry", **common)
    isam2_p99_ms = 1e3 * float(np.percentile(res_i.step_time_s, 99))
    inc, bat = res_i.details, res_b.details
    assert res_b.decisions is not None
    out: dict[str, Any] = {
        "benchmark": "graph",
        "scenario": log.scenario,
        "seed": log.seed,
        "steps": int(res_b.poses.shape[0]),
        "observations": int(np.sum(res_b.decisions.obs_landmark >= 0)),
        "fusion": args.fusion,
        "association": args.association,
        "machine": {"cpus": os.cpu_count(), "load_avg_1min": round(os.getloadavg()[0], 2)},
        "load_log_s": round(load_s, 3),
        "ekf_s": ekf_s,
        "targets": TARGETS,
        "summary": {
            "isam2_total_s": round(inc.total_time_s, 3),
            "isam2_total_cpu_s": round(inc.total_cpu_s, 3),
            "isam2_per_step_p99_ms": round(isam2_p99_ms, 2),
            "batch_total_s": round(bat.total_time_s, 3),
            "batch_total_cpu_s": round(bat.total_cpu_s, 3),
            "batch_solve_s": round(bat.solve_time_s, 3),
        },
        "isam2": _summary(res_i, log),
        "batch": _summary(res_b, log),
        "isam2_final_vs_batch": _agreement(res_i, res_b),
    }
    met: dict[str, bool] = {
        "isam2_total": inc.total_time_s <= TARGETS["isam2_total_s"],
        "isam2_p99": isam2_p99_ms <= TARGETS["isam2_p99_ms"],
        "batch_total": bat.total_time_s <= TARGETS["batch_total_s"],
    }
    if not args.skip_builtin:
        cmp = _same_size_comparison(log, args, ekf, res_b, isam_opts)
        out["same_size_comparison"] = cmp
        c, b = cmp["custom"], cmp["builtin"]
        ratios: dict[str, float] = {
            "batch_lm_cpu": _ratio(c["batch_lm"]["cpu_s"], b["batch_lm"]["cpu_s"]),
            "batch_lm_wall": _ratio(c["batch_lm"]["wall_s"], b["batch_lm"]["wall_s"]),
        }
        if "isam2" in c:
            ratios["isam2_cpu"] = _ratio(c["isam2"]["cpu_s"], b["isam2"]["cpu_s"])
            ratios["isam2_wall"] = _ratio(c["isam2"]["wall_s"], b["isam2"]["wall_s"])
        ratios["batch_lm_cpu_per_linearization"] = _ratio(
            c["batch_lm"]["cpu_ms_per_linearization"], b["batch_lm"]["cpu_ms_per_linearization"]
        )
        ratios["observation_linearize"] = _ratio(
            c["observation_cost"]["linearize_us_per_factor"],
            b["observation_cost"]["linearize_us_per_factor"],
        )
        out["custom_over_builtin"] = ratios
        out["summary"].update(
            {
                "ratio_batch_cpu": ratios["batch_lm_cpu"],
                "ratio_batch_wall": ratios["batch_lm_wall"],
                "ratio_batch_cpu_per_linearization": ratios["batch_lm_cpu_per_linearization"],
                "ratio_isam2_cpu": ratios.get("isam2_cpu"),
                "ratio_isam2_wall": ratios.get("isam2_wall"),
                "batch_lm_cpu_s": {
                    "custom": c["batch_lm"]["cpu_s"],
                    "builtin": b["batch_lm"]["cpu_s"],
                },
                "isam2_cpu_s": {
                    "custom": c.get("isam2", {}).get("cpu_s"),
                    "builtin": b.get("isam2", {}).get("cpu_s"),
                },
                "same_size": cmp["same_size"],
            }
        )
        met["ratio_batch"] = ratios["batch_lm_cpu"] <= TARGETS["ratio"]
        met["ratio_batch_per_linearization"] = (
            ratios["batch_lm_cpu_per_linearization"] <= TARGETS["ratio"]
        )
        if "isam2_cpu" in ratios:
            met["ratio_isam2"] = ratios["isam2_cpu"] <= TARGETS["ratio"]
    out["met"] = met
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
