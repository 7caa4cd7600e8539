"""Monte Carlo over loop600 seeds: how often each of the paper's per-seed criteria holds.

The acceptance tests check the paper's figures on seeds 0–4, one run each.  This script
runs many seeds and reports, per estimator, on how many seeds each criterion holds, so a
miss can be weighed against how often estimators without the EKF's approximations
miss it too (``--estimators``, comma-separated):

* ``ekf`` — the EKF reference as configured by default (the paper's local maps);
* ``ekf_carry`` — the same with ``EKFConfig(carry_seen_steps=1)``: every local map
  starts with the global features seen at the last step, shared as the known map is;
* ``filter`` — iSAM2's filtered estimate (the result's ``filtered`` track) on the same
  log and the default EKF's association decisions;
* ``batch`` — the batch smoother on the same inputs (its anchor uses every step);
* ``draw`` — the known-map draw alone: where an ideal estimator would put the anchor
  (:func:`mapfuse_core.evaluation.known_map_draw_offset`).

Each seed's row is appended to ``--out`` (JSON lines) when done, so a run can be stopped and resumed
(seeds already in the file are skipped); the summary is printed as one JSON object.
``--summarise FILE`` prints the summary of a file only.

    python benchmarks/mc_loop600.py --seeds 0-39 --estimators ekf,ekf_carry,filter,batch,draw \
        --out /tmp/mc.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from ekf_reference import EKFConfig, run_ekf
from mapfuse.metrics import run_metrics
from mapfuse.runner import run
from mapfuse_core.estimate import Anchor, EstimatorResult
from mapfuse_core.evaluation import (
    CHI2_3_95,
    anchor_truth,
    known_map_draw_offset,
    nees_series,
    pose_errors,
    truth_in_global,
)
from mapfuse_core.geometry.se2 import compose, wrap_angle
from mapfuse_core.measlog import MeasurementLog
from mapfuse_core.sim.scenario import build_known_map, load_scenario
from mapfuse_core.sim.simulate import simulate

ESTIMATORS = ("ekf", "ekf_carry", "filter", "batch", "draw")

# name: (run, field it needs, test).  A run lacking the field (the filter has no
# anchor) is not counted on that criterion.
CRITERIA = {
    "max_error_le_0.15": ("fused", "max_m", lambda r: r["max_m"] <= 0.15),
    "nees_within_ge_0.90": ("fused", "nees_within", lambda r: r["nees_within"] >= 0.90),
    "nees_within_ge_0.90_no_fusion": ("plain", "nees_within", lambda r: r["nees_within"] >= 0.90),
    "anchor_le_4cm_2mrad": (
        "fused",
        "anchor_m",
        lambda r: r["anchor_m"] is not None and r["anchor_m"] <= 0.04 and r["anchor_rad"] <= 0.002,
    ),
    "no_wrong_pairing": ("fused", "wrong_pairings", lambda r: r["wrong_pairings"] == 0),
}


def _ekf_metrics(res: EstimatorResult, log: MeasurementLog) -> dict[str, Any]:
    return run_metrics(res, log).to_json()


def _parse_seeds(text: str) -> list[int]:
    seeds: list[int] = []
    for part in text.split(","):
        lo, dash, hi = part.partition("-")
        if not lo.strip().isdigit() or (dash and not hi.strip().isdigit()):
            raise argparse.ArgumentTypeError(f"seeds must look like 0-39 or 0,3,7; got {text!r}")
        seeds += list(range(int(lo), int(hi) + 1)) if dash else [int(lo)]
    return seeds


def _anchor_fields(a: dict[str, Any] | None) -> dict[str, Any]:
    return {
        "anchor_m": None if a is None else a["position_error_m"],
        "anchor_rad": None if a is None else a["heading_error_rad"],
        "wrong_pairings": None if a is None else a["pairings"] - a["correct_pairings"],
    }


def _ekf_row(metrics: dict[str, Any], anchor_nees: float | None) -> dict[str, Any]:
    return {
        "max_m": metrics["position_error_m"]["max"],
        "rmse_m": metrics["position_error_m"]["rmse"],
        "nees_mean": metrics["nees"]["mean"],
        "nees_within": metrics["nees"]["fraction_within_chi2_95"],
        **_anchor_fields(metrics["anchor"]),
        "anchor_nees": anchor_nees,
    }


def run_seed(seed: int, estimators: tuple[str, ...]) -> dict[str, Any]:
    """The chosen estimators on one seed's log (run in a worker process)."""
    scenario = load_scenario("loop600")
    log = simulate(scenario, seed=seed, workers=1).log
    assert log.true_poses is not None
    truth = anchor_truth(log.true_poses, log.known_frame)

    def anchor_nees(a: Anchor | None) -> float | None:
        if a is None:
            return None
        dx = pose_errors(a.x_Wknown_Wglobal[None], truth[None]).dx
        return float(nees_series(dx, a.cov[None])[0])

    row: dict[str, Any] = {"seed": seed}
    # The graph backends take the default fused EKF's association decisions.
    default_fused = run_ekf(log, EKFConfig(), fusion=True)
    for name, carry in (("ekf", 0), ("ekf_carry", 1)):
        if name not in estimators:
            continue
        row[name] = {}
        for fusion in (True, False):
            res = (
                default_fused
                if fusion and not carry
                else run_ekf(log, EKFConfig(carry_seen_steps=carry), fusion=fusion)
            )
            row[name]["fused" if fusion else "plain"] = _ekf_row(
                _ekf_metrics(res, log), anchor_nees(res.anchor)
            )
    if "draw" in estimators:
        # The log's draw against the map's truth (which no draw changes).
        k = log.known_map
        true_params = build_known_map(scenario, np.random.default_rng(0)).true_params
        draw = known_map_draw_offset(k.kinds, k.params, k.covs, true_params)
        ideal = compose(draw.offset, truth)
        row["draw"] = {
            "fused": {
                "anchor_m": math.hypot(*(ideal[:2] - truth[:2])),
                "anchor_rad": abs(float(wrap_angle(ideal[2] - truth[2]))),
                "anchor_nees": draw.nees,
            }
        }
    if "filter" in estimators:
        g = run(log, "isam2", fusion=True, upstream=default_fused).result.filtered
        assert g is not None
        dx = pose_errors(g.poses, truth_in_global(log.true_poses)).dx
        nees = nees_series(dx, g.covs)[1:]
        nees = nees[np.isfinite(nees)]
        row["filter"] = {
            "fused": {
                "max_m": float(np.hypot(dx[:, 0], dx[:, 1]).max()),
                "nees_mean": float(nees.mean()),
                "nees_within": float(np.mean(nees <= CHI2_3_95)),
            }
        }
    if "batch" in estimators:
        batch = run(log, "batch", fusion=True, upstream=default_fused)
        m = batch.metrics.to_json()
        row["batch"] = {
            "fused": {
                "max_m": m["position_error_m"]["max"],
                "nees_mean": m["nees"]["mean"],
                **_anchor_fields(m["anchor"]),
                "anchor_nees": anchor_nees(batch.result.anchor),
            }
        }
    return row


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Per estimator and criterion: seeds passing, seeds tried, and the failing seeds."""
    out: dict[str, Any] = {"seeds": len(rows)}
    for est in ESTIMATORS:
        res: dict[str, Any] = {}
        for crit, (mode, field, ok) in CRITERIA.items():
            tried = [r for r in rows if field in r.get(est, {}).get(mode, {})]
            if not tried:
                continue
            fails = [r["seed"] for r in tried if not ok(r[est][mode])]
            res[crit] = {"pass": len(tried) - len(fails), "of": len(tried), "failing": fails}
        fused = [r[est]["fused"] for r in rows if "fused" in r.get(est, {})]
        for key in ("max_m", "nees_mean", "anchor_m", "anchor_nees"):
            vals = [f[key] for f in fused if f.get(key) is not None]
            if vals:
                res[f"{key}_median"] = round(float(np.median(vals)), 4)
                res[f"{key}_p90"] = round(float(np.quantile(vals, 0.9)), 4)
        nees = [f["anchor_nees"] for f in fused if f.get("anchor_nees") is not None]
        if nees:
            # A consistent 3-dof anchor: mean 3, and 5 % of the seeds above χ²(3, 0.95).
            res["anchor_nees_mean"] = round(float(np.mean(nees)), 3)
            res["anchor_nees_above_7.815"] = f"{sum(v > CHI2_3_95 for v in nees)}/{len(nees)}"
        out[est] = res
    return out


def _read(path: Path) -> list[dict[str, Any]]:
    if not path.exists():
        return []
    rows = []
    for n, line in enumerate(path.read_text().splitlines(), 1):
        try:
            rows.append(json.loads(line))
        except json.JSONDecodeError as e:
            raise SystemExit(f"{path}:{n}: not a JSON line ({e})") from None
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--seeds", type=_parse_seeds, default=_parse_seeds("0-19"))
    ap.add_argument(
        "--estimators",
        default="ekf,ekf_carry,draw",
        help=f"comma-separated, from {','.join(ESTIMATORS)} (default: %(default)s)",
    )
    ap.add_argument("--workers", type=int, default=2, help="seeds run at once (processes)")
    ap.add_argument("--out", type=Path, help="JSON lines, one row per seed (appended)")
    ap.add_argument("--summarise", type=Path, metavar="FILE", help="only summarise FILE")
    args = ap.parse_args()
    if args.summarise is not None:
        print(json.dumps(summarise(_read(args.summarise)), indent=1))
        return
    estimators = tuple(e.strip() for e in args.estimators.split(",") if e.strip())
    if not estimators or not set(estimators) <= set(ESTIMATORS):
        raise SystemExit(f"--estimators: choose from {', '.join(ESTIMATORS)}")
    if args.workers < 1:
        raise SystemExit(f"--workers must be ≥ 1, got {args.workers}")
    rows = _read(args.out) if args.out else []
    done = {r["seed"] for r in rows}
    todo = [s for s in args.seeds if s not in done]
    # One BLAS thread per worker keeps the seeds from competing for the cores (the
    # spawned workers read it before they import numpy).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=args.workers, mp_context=ctx) as pool:
        for row in pool.map(run_seed, todo, [estimators] * len(todo)):
            rows.append(row)
            if args.out:
                with args.out.open("a") as f:
                    f.write(json.dumps(row) + "\n")
    wanted = set(args.seeds)
    print(json.dumps(summarise([r for r in rows if r["seed"] in wanted]), indent=1))


if __name__ == "__main__":
    main()
