"""Consistency over the world regimes that matter, a generated world per run.

Each regime is a set of world-generator arguments (:mod:`mapfuse_core.sim.worldgen`;
vehicle, laser and known-map noise are loop600's): run ``s`` of a regime draws its
world from seed ``s`` and simulates it with seed ``s``, as ``mapfuse montecarlo
--world-per-run`` does.  The regimes (``REGIMES``):

* ``dense`` — loop600's density: a 600 m loop with its 39 walls and 58 trees of radius
  0.27–1.0 m;
* ``sparse`` — a long thin loop: a 583 m corridor (2,333 steps) with 10 walls and 45
  trees of radius 0.3–0.9 m, 4–18 m from the drive, and the 80 m laser;
* ``close`` — large trunks close to the drive: 600 m, 12 walls, 45 trees of radius
  0.5–1.2 m, 2–6 m from the drive;
* ``figure8`` — a 400 m figure-eight with a 40 m laser, 22 walls and 50 trees.

Every regime runs the EKF and batch with and without fusion (``mapfuse.campaign``, one
campaign directory per regime under ``--out``; rerunning into it resumes).  Per
regime, estimator and fusion setting: the ANEES over the steps with its two-sided 95 %
bounds for the number of runs (:func:`mapfuse.campaign.stats.anees_bounds`), the
fraction of steps inside them (and above), the anchor ANEES with its bounds, the RMSE
with its 95 % interval, the wrong pairings accepted, and the map matchings behind the
anchors: matches refused by the EKF's joint tests before fusion
(``AssociationConfig.match_joint_test``, ``match_pairing_test``) and anchors undone
after it (``EKFConfig.anchor_watch``), summed over the runs (the batch rows count the
EKF's matchings they consume).  The JSON report goes to stdout, the markdown table to
``OUT/regimes.md`` and stderr.

    PYTHONPATH=. nice -n 10 python benchmarks/consistency_regimes.py --runs 20 \\
        --workers 1 --out /tmp/regimes
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

from mapfuse.campaign.api import montecarlo
from mapfuse.campaign.spec import parse_world_args
from mapfuse.campaign.stats import anees_bounds
from mapfuse.campaign.summary import GroupSummary

#: Generator arguments of each regime, as ``--world-per-run`` takes them.
REGIMES: dict[str, str] = {
    "dense": "walls=39,trees=58,tree_radius_min_m=0.27,tree_radius_max_m=1.0",
    "sparse": (
        "shape=corridor,loop_length_m=583,walls=10,trees=45,tree_radius_min_m=0.3,"
        "tree_radius_max_m=0.9,tree_clearance_min_m=4,tree_clearance_max_m=18"
    ),
    "close": (
        "walls=12,trees=45,tree_radius_min_m=0.5,tree_radius_max_m=1.2,"
        "tree_clearance_min_m=2,tree_clearance_max_m=6"
    ),
    "figure8": "shape=figure8,laser_range_m=40,walls=22,trees=50,loop_length_m=400",
}
ESTIMATORS = ("ekf", "batch")
#: ``matching.reasons`` keys of a match the EKF refused before fusing it.
REFUSED_BEFORE_FUSION = ("jointly inconsistent", "a pairing inconsistent with the others")
#: ``matching.reasons`` key of an anchor the EKF undid after fusing it.
UNDONE_AFTER_FUSION = "anchor contradicted"


def _round(x: float, digits: int = 3) -> float | None:
    return None if not math.isfinite(x) else round(float(x), digits)


def _bounds(n: int) -> list[float | None]:
    if n == 0:
        return [None, None]
    lo, hi = anees_bounds(n)
    return [_round(float(lo)), _round(float(hi))]


def _reason_total(g: GroupSummary, keys: tuple[str, ...]) -> int:
    return sum(int((r.get("ccda_reasons") or {}).get(k, 0)) for r in g.rows for k in keys)


def group_stats(g: GroupSummary) -> dict[str, Any]:
    """The figures of one estimator with one fusion setting over a regime's runs."""
    n = len(g.seeds)
    anchor, a_lo, a_hi, a_runs = g.anchor_anees
    wrong, wrong_runs = g.wrong_pairings
    rmse = g.interval("rmse_m") if n else None
    return {
        "estimator": g.estimator,
        "fusion": g.fusion,
        "runs": n,
        "failed": list(g.failed),
        "errors": list(g.errors),
        "anees": _round(g.anees.overall),
        "anees_bounds": _bounds(n),
        "steps_inside": _round(g.anees.fraction_inside),
        "steps_above": _round(g.anees.fraction_above),
        "anchor_anees": _round(anchor),
        "anchor_bounds": [_round(a_lo), _round(a_hi)],
        "anchor_runs": a_runs,
        "wrong_pairings": wrong,
        "wrong_pairing_runs": wrong_runs,
        "matches_refused_before_fusion": _reason_total(g, REFUSED_BEFORE_FUSION),
        "anchors_undone_after_fusion": _reason_total(g, (UNDONE_AFTER_FUSION,)),
        "rmse_m": None
        if rmse is None
        else [_round(rmse.value), _round(rmse.low), _round(rmse.high)],
    }


def run_regime(
    name: str, runs: int, out: Path, workers: int, steps: int | None = None
) -> dict[str, Any]:
    """Run regime ``name`` (seeds ``0 … runs − 1``) into ``out/name`` and summarise it."""
    world = parse_world_args(REGIMES[name])
    t0 = time.perf_counter()
    mc = montecarlo(
        "loop600",
        seeds=range(runs),
        estimators=ESTIMATORS,
        fusions=(True, False),
        world=world,
        steps=steps,
        out=out / name,
        workers=workers,
        serial=workers <= 1,
        report=False,
    )
    return {
        "regime": name,
        "world": world,
        "runs": runs,
        "wall_s": round(time.perf_counter() - t0, 1),
        "groups": [group_stats(g) for g in mc.groups],
    }


def _cell(x: Any) -> str:
    return "–" if x is None else f"{x}"


def markdown(report: dict[str, Any]) -> str:
    """The report as one markdown table."""
    head = (
        "| regime | run | runs | ANEES [bounds] | steps inside (above) | anchor ANEES [bounds] "
        "(runs) | wrong pairings (runs) | refused before fusion | undone after | RMSE (m) |"
    )
    lines = [head, "|" + "---|" * 10]
    for reg in report["regimes"]:
        for g in reg["groups"]:
            lo, hi = g["anees_bounds"]
            alo, ahi = g["anchor_bounds"]
            fused = g["fusion"]
            anchor = (
                f"{_cell(g['anchor_anees'])} [{_cell(alo)}, {_cell(ahi)}] ({g['anchor_runs']})"
                if fused
                else "n/a"
            )
            wrong = f"{g['wrong_pairings']} ({g['wrong_pairing_runs']})" if fused else "n/a"
            refused = _cell(g["matches_refused_before_fusion"]) if fused else "n/a"
            undone = _cell(g["anchors_undone_after_fusion"]) if fused else "n/a"
            rmse = g["rmse_m"]
            rmse_txt = "–" if rmse is None else f"{rmse[0]} [{rmse[1]}, {rmse[2]}]"
            inside = (
                "–"
                if g["steps_inside"] is None
                else f"{100 * g['steps_inside']:.1f} % ({100 * g['steps_above']:.1f} %)"
            )
            failed = f", {len(g['failed'])} failed" if g["failed"] else ""
            lines.append(
                f"| {reg['regime']} | {g['estimator']} {'with' if fused else 'without'} fusion "
                f"| {g['runs']}{failed} | {_cell(g['anees'])} [{_cell(lo)}, {_cell(hi)}] "
                f"| {inside} | {anchor} | {wrong} | {refused} | {undone} | {rmse_txt} |"
            )
    return "\n".join(lines)


def _regimes(text: str) -> list[str]:
    names = [s.strip() for s in text.split(",") if s.strip()]
    bad = [n for n in names if n not in REGIMES]
    if bad or not names:
        raise argparse.ArgumentTypeError(
            f"unknown regime {', '.join(bad) or '(none)'}; choose from {', '.join(REGIMES)}"
        )
    return names


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--runs", type=int, default=20, help="worlds per regime (seeds 0 … N−1)")
    ap.add_argument(
        "--regimes", type=_regimes, default=list(REGIMES), help="comma-separated (default: all)"
    )
    ap.add_argument("--workers", type=int, default=1, help="dask workers (1: in this process)")
    ap.add_argument("--steps", type=int, help="steps per run (default: the whole drive)")
    ap.add_argument("--out", required=True, help="directory of the campaigns (resumable)")
    args = ap.parse_args(argv)
    if args.runs < 1:
        raise SystemExit(f"--runs must be >= 1, got {args.runs}")
    out = Path(args.out)
    report = {
        "runs": args.runs,
        "estimators": list(ESTIMATORS),
        "regimes": [run_regime(r, args.runs, out, args.workers, args.steps) for r in args.regimes],
    }
    print(json.dumps(report, indent=1))
    table = markdown(report)
    out.mkdir(parents=True, exist_ok=True)
    (out / "regimes.md").write_text(table + "\n")
    print(table, file=sys.stderr)


if __name__ == "__main__":
    main()
