"""The front end on CARMEN logs: lines, CCDA, association and estimators (prints JSON).

For every corrected log given (``--logs``; default every ``*-corrected.log*`` in
``--data``/carmen), every scan count of ``--steps`` (the whole log when absent; a
prefix of the log mimics a shorter log) and every seed of the simulated odometry:

* **lines**: scans, line observations per scan, walls of the floor plan, the line
  NEES per degree of freedom of every observation against its plan wall at the
  reference pose (mean, median; :func:`~mapfuse_core.data.datasets.line_nees`);
* **CCDA** (EKF with the plan): attempts and their outcomes (``accepted``, every
  refusal reason, ``search_limit`` the budget's), and the accepted match's pairings
  judged against the reference labels (``same_wall``);
* **association** (EKF, with and without the plan; ``--ekf`` overrides its options):
  the wrong re-observations, and those of them a join made
  (:func:`wrong_reobservations` defines them); the observations off their landmark's
  wall, unlabelled ones included (:func:`off_wall_observations`);
* **estimators** (``--estimators``; EKF, batch, iSAM2 on the EKF's decisions with the
  ``carmen:`` profile's Cauchy kernel, another kernel as ``batch+huber``, none as
  ``batch+gauss``; ``batch@truth`` pairs the observations by their reference labels
  instead, the plan's walls included, and ``isam2@own`` makes its own association and
  map match) with and without the plan:
  position RMSE and max against the reference, mean pose NEES with its two-sided
  95 % acceptance region, run time.

One JSON line per (log, steps, seed) and, after every log, a summary line over the
seeds; ``--markdown`` prints the summary tables at the end.

    OPENBLAS_NUM_THREADS=1 nice -n 10 python benchmarks/carmen_frontend.py \\
        --logs csail intel --steps 237 440 0 --seeds 0 --estimators ekf --markdown
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

import numpy as np
from scipy.stats import chi2

from mapfuse.campaign.stats import anees_bounds
from mapfuse.runner import run
from mapfuse_core.data.datasets import (
    CarmenOptions,
    FloorPlan,
    LineModelShape,
    build_floor_plan,
    label_with_plan,
    line_nees,
    load_carmen,
    same_wall,
    wall_d2,
)
from mapfuse_core.estimate import EstimatorResult
from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog


@dataclass(frozen=True)
class Reobservations:
    """Wrong re-observations of one run (:func:`wrong_reobservations`)."""

    judged: int
    """Re-observations with a reference label on a landmark with a majority label."""
    wrong: int
    """Of those, on another line than the landmark's majority wall: not collinear with
    it (``same_wall`` within the plan's ρ and α tolerances, at any distance along the
    line; a line landmark constrains only the line)."""
    wrong_strict: int
    """Of those, with a label other than the majority label (collinear pieces of one
    line count as wrong here)."""
    wrong_at_join: int
    """Of the wrong ones, those a join made: the observation agrees with the majority
    wall of its local-map feature, which a join merged into another wall's landmark
    (the rest the measurement association made)."""


def wrong_reobservations(
    obs_landmark: np.ndarray,
    labels: np.ndarray,
    steps: np.ndarray,
    plan: FloorPlan,
    obs_local: np.ndarray | None = None,
) -> Reobservations:
    """Re-observations the association sent to a landmark of another wall.

    ``obs_landmark[i]``: the landmark (final track) observation ``i`` went to, −1 for
    none; ``labels[i]``: its reference label (the plan wall it lies on at the
    reference pose, −1 for none); ``steps[i]``: its step.  A *re-observation* is an
    observation of a landmark that existed before its step: every observation of a
    landmark but those of the landmark's first step.  It is *judged* when it has a
    label and its landmark has a majority label (:func:`landmark_labels`: the wall
    most of the landmark's labelled observations lie on), and *wrong* when its label
    is a wall on another line than the majority wall's (``same_wall`` at any gap: a
    line landmark's observations of a collinear piece beyond a doorway are
    observations of its line).  ``obs_local[i]``: the local-map feature observation
    ``i`` went to (``EKFDetails.obs_local_track``), which tells a join's wrong pairings
    from the measurement association's.
    """
    lm = np.asarray(obs_landmark)
    ids = sorted({int(v) for v in lm.tolist() if v >= 0})
    majority = dict(zip(ids, landmark_labels(lm, labels, ids), strict=True))
    loc = lm if obs_local is None else np.asarray(obs_local)
    loc_ids = sorted({int(v) for v in loc.tolist() if v >= 0})
    local_majority = dict(zip(loc_ids, landmark_labels(loc, labels, loc_ids), strict=True))
    first: dict[int, int] = {}
    for i in np.flatnonzero(lm >= 0).tolist():
        first.setdefault(int(lm[i]), int(steps[i]))
    judged = wrong = strict = at_join = 0
    same: dict[tuple[int, int], bool] = {}

    def on_line(a: int, b: int) -> bool:
        if a == b:
            return True
        if (a, b) not in same:
            same[(a, b)] = same_wall(plan, a, b, gap_m=math.inf)
        return same[(a, b)]

    for i in np.flatnonzero((lm >= 0) & (labels >= 0)).tolist():
        L = int(lm[i])
        if int(steps[i]) == first[L] or majority[L] < 0:
            continue
        judged += 1
        a, b = int(labels[i]), majority[L]
        strict += a != b
        if on_line(a, b):
            continue
        wrong += 1
        local = local_majority.get(int(loc[i]), -1)
        at_join += local >= 0 and on_line(a, local)
    return Reobservations(judged, wrong, strict, at_join)


@dataclass(frozen=True)
class OffWall:
    """Observations off their landmark's wall (:func:`off_wall_observations`)."""

    judged: int
    """Line observations, each landmark's first ones included, of landmarks with a
    majority label."""
    off: int
    """Of those, not on the line of the landmark's majority wall: labelled with a wall on
    another line, or unlabelled and outside the χ²(2) gate of the majority wall at the
    reference pose."""
    landmarks: int
    """Landmarks with at least one such observation."""
    far: int
    """Of the unlabelled ones off the wall, those beyond :data:`FAR_OFF_WALL`: past the
    gate lies the tail of the line errors of segments that are on the wall but were
    left unlabelled (a piece past the plan wall's end), far past it lie other
    structures (a recess, a jog, the next wall)."""


OFF_WALL_GATE = float(chi2.ppf(0.999, 2))
"""The gate of :func:`off_wall_observations`: the one reference labels are given with
(:func:`~mapfuse_core.data.datasets.reference_labels`)."""
FAR_OFF_WALL = 100.0
"""Squared Mahalanobis distance (10 σ) beyond which an unlabelled observation counts
as far off its landmark's wall (:attr:`OffWall.far`)."""


def off_wall_observations(
    obs_landmark: np.ndarray, log: MeasurementLog, plan: FloorPlan
) -> OffWall:
    """Observations the association put on a landmark of another wall, unlabelled ones
    included.

    :func:`wrong_reobservations` judges labelled re-observations only.  A segment with
    no label (a recess, a cabinet, a wall left out of the plan, a piece past a wall's
    end) merged into a plan wall's landmark escapes it, and so does the landmark's first
    observation.  Here every line observation of a landmark with a majority label
    (``log.feat_true_id``, :func:`landmark_labels`) is judged against that wall at the
    reference pose: a labelled one is off when its wall is on another line
    (``same_wall`` at any gap), an unlabelled one when its squared Mahalanobis distance
    to the wall (:func:`~mapfuse_core.data.datasets.wall_d2`) exceeds
    :data:`OFF_WALL_GATE`.
    """
    lm = np.asarray(obs_landmark)
    labels = np.asarray(log.feat_true_id)
    lines = (lm >= 0) & (log.feat_kind == FeatureKind.LINE)
    ids = sorted({int(v) for v in lm[lines].tolist()})
    majority = dict(zip(ids, landmark_labels(lm, labels, ids), strict=True))
    judged = off = far = 0
    mixed: set[int] = set()
    for i in np.flatnonzero(lines).tolist():
        L = int(lm[i])
        w = majority[L]
        if w < 0:
            continue
        judged += 1
        a = int(labels[i])
        if a >= 0:
            bad = a != w and not same_wall(plan, a, w, gap_m=math.inf)
        else:
            d2 = wall_d2(log, i, plan.walls, w)
            bad = d2 > OFF_WALL_GATE
            far += d2 > FAR_OFF_WALL
        if bad:
            off += 1
            mixed.add(L)
    return OffWall(judged, off, len(mixed), far)


def _line_nees(full: MeasurementLog, plan: FloorPlan) -> dict[str, float]:
    """The line NEES per dof of the whole log against its plan (mean, median): the
    scans and the reference poses, so the same for every seed of the odometry."""
    nees = line_nees(full, plan) / 2.0
    return {
        "line_nees_per_dof_mean": float(nees.mean()) if nees.size else math.nan,
        "line_nees_per_dof_median": float(np.median(nees)) if nees.size else math.nan,
    }


def _lines(log: MeasurementLog, plan: FloorPlan) -> dict[str, Any]:
    """Scans, line observations per scan and plan walls of ``log``."""
    n_lines = int(np.count_nonzero(log.feat_kind == FeatureKind.LINE))
    return {
        "scans": log.n_steps,
        "lines_per_scan": n_lines / log.n_steps,
        "plan_walls": len(plan.walls),
    }


def _estimator_row(r: Any, cpu: float) -> dict[str, Any]:
    m = r.metrics
    nees = m.nees
    iv = nees.mean_interval
    return {
        "rmse_m": m.position_error.rmse,
        "max_m": m.position_error.max,
        "nees_mean": nees.mean,
        "nees_interval": list(iv.interval_95) if iv is not None else None,
        "nees_effective_samples": iv.effective_samples if iv is not None else None,
        "runtime_s": m.runtime.total,
        "cpu_s": cpu,
    }


def _ekf_extras(res: EstimatorResult, log: MeasurementLog, plan: FloorPlan) -> dict[str, Any]:
    out: dict[str, Any] = {}
    local = getattr(res.details, "obs_local_track", None)
    ro = wrong_reobservations(
        res.decisions.obs_landmark, log.feat_true_id, log.feat_step, plan, local
    )
    out["reobs"] = {
        "judged": ro.judged,
        "wrong": ro.wrong,
        "wrong_strict": ro.wrong_strict,
        "wrong_at_join": ro.wrong_at_join,
    }
    ow = off_wall_observations(res.decisions.obs_landmark, log, plan)
    out["off_wall"] = {
        "judged": ow.judged,
        "off": ow.off,
        "landmarks": ow.landmarks,
        "far": ow.far,
    }
    if res.matching is not None:
        out["ccda"] = {"attempts": res.matching.attempts, **res.matching.reasons}
    if res.anchor is not None:
        judged = [same_wall(plan, a, b) for a, b in res.anchor.pairings if a >= 0]
        out["match"] = {
            "step": res.anchor.accepted_at_step,
            "pairings": len(res.anchor.pairings),
            "judged": len(judged),
            "correct": int(sum(judged)),
        }
    return out


def _one(
    path: Path,
    seed: int,
    steps: int,
    estimators: list[str],
    full: MeasurementLog,
    plan: FloorPlan,
    ekf_options: dict[str, Any],
) -> dict[str, Any]:
    log = label_with_plan(full, plan)
    if steps < log.n_steps:
        log = log.head(steps)
    row: dict[str, Any] = {"log": path.name.split("-corrected")[0], "seed": seed}
    row.update(_lines(log, plan))
    for fusion in (True, False):
        key = "plan" if fusion else "none"
        ekf = None
        for est in estimators:
            name, kw = backend_and_kernel(est)
            if est == "ekf":
                kw = ekf_options
            c0 = time.process_time()
            own = kw.get("association") == "own"
            r = run(log, name, fusion=fusion, upstream=None if est == "ekf" or own else ekf, **kw)
            cpu = time.process_time() - c0
            row[f"{est}_{key}"] = _estimator_row(r, cpu)
            if est == "ekf":
                ekf = r.result
                row[f"ekf_{key}"].update(_ekf_extras(r.result, log, plan))
    return row


def backend_and_kernel(est: str) -> tuple[str, dict[str, Any]]:
    """``NAME``, ``NAME+KERNEL``, ``NAME@ASSOCIATION`` or ``NAME+KERNEL@ASSOCIATION``
    → the estimator's name and the override of its options: the kernel's (``gauss``:
    no kernel; without one, the profile's) and the association: ``@truth`` by
    reference labels, ``@own`` the graph backend's own (iSAM2 only), instead of the
    EKF's decisions."""
    rest, _, assoc = est.partition("@")
    if assoc not in ("", "truth", "own"):
        raise ValueError(f"unknown association {assoc!r} in {est!r} (@truth or @own)")
    name, _, kernel = rest.partition("+")
    kw: dict[str, Any] = {"association": assoc} if assoc else {}
    if kernel:
        kw["graph"] = {"robust": None if kernel == "gauss" else kernel}
    return name, kw


def _anees(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """ANEES over the runs: the mean of their means, with the 95 % acceptance region of
    a consistent estimator from their effective samples summed, and the median and the
    largest of the runs' means (one run far off carries the mean)."""
    runs = [r[key] for r in rows if key in r]
    means = [x["nees_mean"] for x in runs]
    n_eff = sum(x["nees_effective_samples"] or 0.0 for x in runs)
    lo, hi = (float(b) for b in anees_bounds(n_eff))
    return {
        "anees": statistics.fmean(means),
        "interval": [lo, hi],
        "run_median": statistics.median(means),
        "run_max": max(means),
        "rmse_median_m": statistics.median(x["rmse_m"] for x in runs),
        "max_median_m": statistics.median(x["max_m"] for x in runs),
        "runtime_median_s": statistics.median(x["runtime_s"] for x in runs),
    }


def _summary(rows: list[dict[str, Any]], estimators: list[str]) -> dict[str, Any]:
    ccda: Counter[str] = Counter()
    for r in rows:
        ccda.update(r["ekf_plan"].get("ccda", {}))
    matches = [r["ekf_plan"]["match"] for r in rows if "match" in r["ekf_plan"]]
    out: dict[str, Any] = {
        "log": rows[0]["log"],
        "scans": rows[0]["scans"],
        "seeds": len(rows),
        "lines_per_scan": rows[0]["lines_per_scan"],
        "line_nees_per_dof_mean": rows[0]["line_nees_per_dof_mean"],
        "line_nees_per_dof_median": rows[0]["line_nees_per_dof_median"],
        "ccda": dict(ccda),
        "anchored_runs": len(matches),
        "runs_ending_at_budget": sum(
            1
            for r in rows
            if "match" not in r["ekf_plan"] and r["ekf_plan"]["ccda"].get("search_limit", 0)
        ),
        "matches_all_correct": sum(1 for m in matches if m["correct"] == m["judged"]),
        "judged_correct": sum(m["correct"] for m in matches),
        "judged": sum(m["judged"] for m in matches),
    }
    for key in ("plan", "none"):
        j = sum(r[f"ekf_{key}"]["reobs"]["judged"] for r in rows)
        w = sum(r[f"ekf_{key}"]["reobs"]["wrong"] for r in rows)
        s = sum(r[f"ekf_{key}"]["reobs"]["wrong_strict"] for r in rows)
        jn = sum(r[f"ekf_{key}"]["reobs"]["wrong_at_join"] for r in rows)
        out[f"wrong_reobs_at_join_{key}_pct"] = 100.0 * jn / j if j else math.nan
        out[f"wrong_reobs_{key}_pct"] = 100.0 * w / j if j else math.nan
        out[f"wrong_reobs_strict_{key}_pct"] = 100.0 * s / j if j else math.nan
        oj = sum(r[f"ekf_{key}"]["off_wall"]["judged"] for r in rows)
        oo = sum(r[f"ekf_{key}"]["off_wall"]["off"] for r in rows)
        of = sum(r[f"ekf_{key}"]["off_wall"]["far"] for r in rows)
        out[f"off_wall_{key}_pct"] = 100.0 * oo / oj if oj else math.nan
        out[f"far_off_wall_{key}_pct"] = 100.0 * of / oj if oj else math.nan
        for est in estimators:
            out[f"{est}_{key}"] = _anees(rows, f"{est}_{key}")
    return out


def _markdown(summaries: list[dict[str, Any]], estimators: list[str]) -> str:
    lines = [
        "| log | scans | lines/scan | line NEES/dof mean, median | CCDA attempts: outcomes "
        "| anchored runs | judged pairings correct | runs ending at budget "
        "| wrong re-obs % plan / none (strict) | of which at joins % plan / none "
        "| off-wall obs % plan / none (far off) |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        oc = ", ".join(f"{k} {v}" for k, v in sorted(s["ccda"].items()) if k != "attempts")
        lines.append(
            f"| {s['log']} | {s['scans']} | {s['lines_per_scan']:.2f} "
            f"| {s['line_nees_per_dof_mean']:.2f}, {s['line_nees_per_dof_median']:.2f} "
            f"| {s['ccda'].get('attempts', 0)}: {oc} | {s['anchored_runs']} / {s['seeds']} "
            f"| {s['judged_correct']} / {s['judged']} | {s['runs_ending_at_budget']} "
            f"| {s['wrong_reobs_plan_pct']:.1f} / {s['wrong_reobs_none_pct']:.1f} "
            f"({s['wrong_reobs_strict_plan_pct']:.1f} / {s['wrong_reobs_strict_none_pct']:.1f}) "
            f"| {s['wrong_reobs_at_join_plan_pct']:.1f} / {s['wrong_reobs_at_join_none_pct']:.1f} "
            f"| {s['off_wall_plan_pct']:.1f} / {s['off_wall_none_pct']:.1f} "
            f"({s['far_off_wall_plan_pct']:.2f} / {s['far_off_wall_none_pct']:.2f}) |"
        )
    lines += [
        "",
        "| log | scans | estimator | plan | RMSE median (m) | max median (m) "
        "| ANEES [95 % region] | run's mean NEES: median, max | run time median (s) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for s in summaries:
        for est in estimators:
            for key in ("plan", "none"):
                a = s[f"{est}_{key}"]
                lines.append(
                    f"| {s['log']} | {s['scans']} | {est} | {key} | {a['rmse_median_m']:.2f} "
                    f"| {a['max_median_m']:.2f} | {a['anees']:.1f} "
                    f"[{a['interval'][0]:.2f}, {a['interval'][1]:.2f}] "
                    f"| {a['run_median']:.1f}, {a['run_max']:.1f} "
                    f"| {a['runtime_median_s']:.1f} |"
                )
    return "\n".join(lines)


def resolve_logs(data: Path, names: list[str] | None) -> list[Path]:
    """The CARMEN logs named (files, or names in ``data``/carmen), every corrected one
    there when none is named."""
    folder = data / "carmen"
    if not names:
        return sorted(folder.glob("*-corrected.log*"))
    out = []
    for n in names:
        p = Path(n)
        if not p.exists():
            hits = sorted(folder.glob(f"{n}*-corrected.log*"))
            if not hits:
                raise SystemExit(f"no CARMEN log {n!r} (neither a file nor in {folder})")
            p = hits[0]
        out.append(p)
    return out


def add_log_arguments(ap: argparse.ArgumentParser) -> None:
    """``--data``, ``--logs`` (:func:`resolve_logs`) and ``--seeds`` of the simulated
    odometry: the arguments every CARMEN benchmark takes."""
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--logs", nargs="*", help="files, or names in --data/carmen (csail, intel…)")
    ap.add_argument("--seeds", type=int, nargs="+", default=[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_log_arguments(ap)
    ap.add_argument(
        "--steps", type=int, nargs="+", default=[0], help="scans to run (0: the whole log)"
    )
    ap.add_argument(
        "--estimators",
        default="ekf",
        help="comma list: ekf,batch,isam2; NAME+KERNEL for a graph backend with another "
        "robust kernel than the profile's (batch+huber; batch+gauss for none)",
    )
    ap.add_argument(
        "--ekf",
        type=json.loads,
        default={},
        help="JSON overrides of the EKF's options, e.g. "
        '\'{"data_association": {"map_method": "nn"}}\'',
    )
    ap.add_argument(
        "--line-model-error",
        default="profile",
        choices=("correlated", "independent", "profile"),
        help="CarmenOptions.line_model_error: where the line model-error terms come from",
    )
    ap.add_argument(
        "--line-model-gate",
        default="weight",
        choices=("weight", "alone"),
        help="CarmenOptions.line_model_gate: which line terms the gates take "
        "(alone: each observation's error alone; needs --line-model-error correlated)",
    )
    ap.add_argument(
        "--line-model-shape",
        default="constant",
        choices=get_args(LineModelShape),
        help="CarmenOptions.line_model_shape: one σ on every line's ρ, or a part falling "
        "as 1/length beside it (needs --line-model-error correlated or independent)",
    )
    ap.add_argument("--markdown", action="store_true")
    args = ap.parse_args()
    terms = {
        "line_model_error": args.line_model_error,
        "line_model_gate": args.line_model_gate,
        "line_model_shape": args.line_model_shape,
    }
    try:
        CarmenOptions(**terms)
    except ValueError as exc:
        ap.error(str(exc))
    estimators = [e for e in args.estimators.split(",") if e]
    if estimators[0] != "ekf":
        ap.error("--estimators must start with ekf (the graph backends take its decisions)")
    summaries = []
    for path in resolve_logs(args.data, args.logs):
        fulls = {
            s: load_carmen(
                path,
                options=CarmenOptions(seed=s, **terms),
            )
            for s in args.seeds
        }
        first = next(iter(fulls.values()))
        n_full = first.n_steps
        # The plan is built from the scans at the reference poses: one for every seed.
        plan = build_floor_plan(first)
        nees = _line_nees(first, plan)
        scans = sorted({min(s or n_full, n_full) for s in args.steps})
        for steps in scans:
            rows = []
            for seed in args.seeds:
                row = _one(path, seed, steps, estimators, fulls[seed], plan, args.ekf)
                rows.append({**row, **nees})
                print(json.dumps(rows[-1]), flush=True)
            summaries.append(_summary(rows, estimators))
            print(json.dumps({"summary": summaries[-1]}), flush=True)
    if args.markdown:
        print(_markdown(summaries, estimators))


if __name__ == "__main__":
    main()
