"""The EKF on CARMEN logs over seeds, with and without the floor plan (prints JSON).

For every corrected log in ``--data``/carmen (or the ``--logs`` given) and every seed
of the simulated odometry: the EKF with the ``carmen:`` profile, once with the floor
plan as known map and once without.  Each run prints one JSON line: CCDA's outcomes,
the accepted match's pairings judged against the reference labels (``same_wall``:
a collinear piece of the labelled wall counts as right), the anchor's error, position
RMSE / max against the reference, mean pose NEES and CPU time.  A summary line per
log follows.  ``--line-gap M`` replaces the association's ``line_gap_m``
(``docs/results/carmen.md`` gives the sweep).

    PYTHONPATH=. python benchmarks/carmen_ccda.py --seeds 0 8
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

from mapfuse.carmen_input import load_carmen_input
from mapfuse.runner import run
from mapfuse_core.data.datasets import (
    CarmenOptions,
    build_floor_plan,
    carmen_association,
    load_carmen,
    same_wall,
)


def _row(path: Path, seed: int, known_map: str, gap: float | None) -> dict[str, Any]:
    log = load_carmen_input(f"carmen:{path}", seed=seed, known_map=known_map)
    overrides: dict[str, Any] = {}
    if gap is not None:
        overrides["data_association"] = dataclasses.replace(carmen_association(), line_gap_m=gap)
    c0 = time.process_time()
    r = run(log, "ekf", **overrides)
    cpu = time.process_time() - c0
    m = r.metrics
    assert m.position_error is not None  # a corrected log has its reference
    assert m.nees is not None
    row: dict[str, Any] = {
        "log": path.name,
        "seed": seed,
        "known_map": known_map,
        "line_gap_m": gap if gap is not None else carmen_association().line_gap_m,
        "rmse_m": m.position_error.rmse,
        "max_m": m.position_error.max,
        "nees_mean": m.nees.mean,
        "cpu_s": cpu,
    }
    res = r.result
    if res.matching is not None:
        row["ccda"] = dict(res.matching.reasons)
    if res.anchor is not None:
        assert m.anchor is not None
        assert m.anchor.position_error_m is not None  # against the reference
        assert m.anchor.heading_error_rad is not None
        plan = build_floor_plan(load_carmen(path, options=CarmenOptions(seed=seed)))
        judged = [same_wall(plan, a, b) for a, b in res.anchor.pairings if a >= 0]
        row.update(
            pairings=len(res.anchor.pairings),
            judged=len(judged),
            correct=int(sum(judged)),
            anchor_error_m=m.anchor.position_error_m,
            anchor_error_deg=math.degrees(m.anchor.heading_error_rad),
        )
    return row


def _summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    plan = [r for r in rows if r["known_map"] == "floorplan"]
    none = [r for r in rows if r["known_map"] == "none"]
    accepted = [r for r in plan if "pairings" in r]
    return {
        "log": rows[0]["log"],
        "line_gap_m": rows[0]["line_gap_m"],
        "seeds": len(plan),
        "accepted": len(accepted),
        "all_pairings_correct": sum(1 for r in accepted if r["correct"] == r["judged"]),
        "judged_correct": sum(r["correct"] for r in accepted),
        "judged": sum(r["judged"] for r in accepted),
        "rmse_median_plan_m": statistics.median(r["rmse_m"] for r in plan),
        "rmse_median_none_m": statistics.median(r["rmse_m"] for r in none),
        "plan_lower_than_none": sum(
            1 for p, n in zip(plan, none, strict=True) if p["rmse_m"] < n["rmse_m"]
        ),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path("../shared/data"))
    ap.add_argument("--logs", type=Path, nargs="*", help="CARMEN logs (default: --data/carmen)")
    ap.add_argument("--seeds", type=int, nargs=2, default=(0, 4), metavar=("FIRST", "STOP"))
    ap.add_argument("--line-gap", type=float, default=None, help="line_gap_m (m)")
    args = ap.parse_args()
    if args.seeds[0] >= args.seeds[1]:
        ap.error(f"--seeds FIRST STOP needs FIRST < STOP, got {args.seeds[0]} {args.seeds[1]}")
    logs = args.logs or sorted((args.data / "carmen").glob("*-corrected.log*"))
    if not logs:
        raise SystemExit(f"no corrected CARMEN log in {args.data / 'carmen'}")
    for path in logs:
        rows = []
        for seed in range(*args.seeds):
            for known_map in ("floorplan", "none"):
                rows.append(_row(path, seed, known_map, args.line_gap))
                print(json.dumps(rows[-1]), flush=True)
        print(json.dumps({"summary": _summary(rows)}), flush=True)


if __name__ == "__main__":
    main()
