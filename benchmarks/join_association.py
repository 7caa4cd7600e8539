"""How a join pairs a local map's features with the global map, on simulated logs
(prints JSON).

Each log (``--scenario``, one per seed of ``--seeds``) is run by the EKF with and
without fusion under every join rule of :data:`RULES`:
``AssociationConfig.map_method`` (nearest neighbour or JCBB over the local map's
features) and ``map_ambiguity`` (take the nearest of two incompatible targets, or
refuse the feature).  Per run: position RMSE, mean pose NEES, the fraction of steps
with the NEES within its χ² 95 % bound, and the line and circle landmarks against the
world features they stand for (the extra ones are duplicates) with the observations
on a landmark of another feature.  One JSON line per run is appended to ``--out``
(runs already there are skipped, so a campaign resumes); then the summary per rule
and fusion is printed: means, and each rule's paired RMSE ratio and NEES difference
against ``nn/nearest`` with Student-t 95 % intervals.

    OPENBLAS_NUM_THREADS=1 nice -n 10 python benchmarks/join_association.py \\
        --seeds 0-29 --out /tmp/join_association.jsonl
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import t as student_t

from mapfuse.campaign.spec import parse_seeds
from mapfuse.runner import load, run
from mapfuse_core.evaluation.labels import landmark_labels
from mapfuse_core.geometry.features import FeatureKind
from mapfuse_core.measlog import MeasurementLog

RULES: dict[str, dict[str, str]] = {
    "nn/nearest": {"map_method": "nn", "map_ambiguity": "nearest"},
    "jcbb/nearest": {"map_method": "jcbb", "map_ambiguity": "nearest"},
    "nn/refuse": {"map_method": "nn", "map_ambiguity": "refuse"},
    "jcbb/refuse": {"map_method": "jcbb", "map_ambiguity": "refuse"},
}
"""Join rules: ``map_method/map_ambiguity``; the first is the default."""


def landmark_counts(log: MeasurementLog, obs_landmark: np.ndarray) -> dict[str, int]:
    """Per feature kind: landmarks with a labelled observation, the world features they
    stand for (their majority labels), and the labelled observations on a landmark of
    another feature."""
    lm, lab = np.asarray(obs_landmark), log.feat_true_id
    ids = sorted({int(v) for v in lm.tolist() if v >= 0})
    majority = dict(zip(ids, landmark_labels(lm, lab, ids), strict=True))
    out: dict[str, int] = {}
    for kind in (FeatureKind.LINE, FeatureKind.CIRCLE):
        sel = np.flatnonzero((lm >= 0) & (lab >= 0) & (log.feat_kind == kind))
        landmarks = {int(lm[i]) for i in sel}
        name = kind.name.lower()
        out[f"{name}_landmarks"] = len(landmarks)
        out[f"{name}_features"] = len({majority[m] for m in landmarks})
        out[f"{name}_wrong_obs"] = sum(1 for i in sel if majority[int(lm[i])] != lab[i])
    return out


def _one(log: MeasurementLog, seed: int, rule: str, fusion: bool) -> dict[str, Any]:
    r = run(log, "ekf", fusion=fusion, data_association=RULES[rule])
    m = r.metrics
    return {
        "seed": seed,
        "rule": rule,
        "fusion": fusion,
        "rmse_m": m.position_error.rmse,
        "nees_mean": m.nees.mean,
        "inside": m.nees.fraction_within_chi2_95,
        **landmark_counts(log, r.result.decisions.obs_landmark),
    }


def _interval(values: list[float]) -> list[float]:
    n = len(values)
    mean = statistics.fmean(values)
    if n < 2:
        return [mean, mean]
    half = float(student_t.ppf(0.975, n - 1)) * statistics.stdev(values) / math.sqrt(n)
    return [mean - half, mean + half]


def summarise(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per rule and fusion: means, and the paired comparison with ``nn/nearest``."""
    base = {(r["seed"], r["fusion"]): r for r in rows if r["rule"] == "nn/nearest"}
    out = []
    for rule in RULES:
        for fusion in (True, False):
            sel = [r for r in rows if r["rule"] == rule and r["fusion"] == fusion]
            if not sel:
                continue
            paired = [(r, base[(r["seed"], fusion)]) for r in sel if (r["seed"], fusion) in base]
            ratio = [r["rmse_m"] / b["rmse_m"] for r, b in paired]
            dnees = [r["nees_mean"] - b["nees_mean"] for r, b in paired]
            out.append(
                {
                    "rule": rule,
                    "fusion": fusion,
                    "runs": len(sel),
                    "rmse_m": statistics.fmean(r["rmse_m"] for r in sel),
                    "nees_mean": statistics.fmean(r["nees_mean"] for r in sel),
                    "inside": statistics.fmean(r["inside"] for r in sel),
                    "line_landmarks": statistics.fmean(r["line_landmarks"] for r in sel),
                    "line_features": statistics.fmean(r["line_features"] for r in sel),
                    "wrong_obs": sum(r["line_wrong_obs"] + r["circle_wrong_obs"] for r in sel),
                    "rmse_ratio_95": _interval(ratio) if ratio else None,
                    "nees_difference_95": _interval(dnees) if dnees else None,
                }
            )
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="loop600")
    ap.add_argument("--seeds", type=parse_seeds, default=parse_seeds("0-29"))
    ap.add_argument("--rules", default=",".join(RULES), help="comma list of RULES")
    ap.add_argument("--out", type=Path, required=True, help="JSONL, appended and resumed")
    args = ap.parse_args()
    rules = [r for r in args.rules.split(",") if r]
    unknown = sorted(set(rules) - set(RULES))
    if unknown:
        ap.error(f"unknown rules {unknown}; known: {', '.join(RULES)}")
    rows = [json.loads(x) for x in args.out.read_text().splitlines()] if args.out.exists() else []
    done = {(r["seed"], r["rule"], r["fusion"]) for r in rows}
    with args.out.open("a") as f:
        for seed in args.seeds:
            todo = [(r, fu) for r in rules for fu in (True, False) if (seed, r, fu) not in done]
            if not todo:
                continue
            log = load(args.scenario, seed=seed)
            for rule, fusion in todo:
                row = _one(log, seed, rule, fusion)
                rows.append(row)
                f.write(json.dumps(row) + "\n")
                f.flush()
    print(json.dumps({"scenario": args.scenario, "summary": summarise(rows)}, indent=1))


if __name__ == "__main__":
    main()
