"""Change detection and fused accuracy over seeds (``docs/changes.md``).

For every seed: loop600 cut to ``--steps`` steps, once with its known map and once
with ``--moved``/``--removed``/``--added`` of it changed (moves 0.3–5 m, lines turned
0.05–0.3 rad); the EKF runs with fusion on both; the changed run is classified and
scored, and both runs' position RMSE and mean NEES are recorded.  One JSON line per
seed is appended to ``--out``.

    PYTHONPATH=. python benchmarks/changes_mc.py --seeds 0 20 --out /tmp/changes.jsonl
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

from mapfuse.changes import detect_changes
from mapfuse.run import run
from mapfuse_core.evaluation.changes import ChangeParams
from mapfuse_core.evaluation.changes.generate import with_changes
from mapfuse_core.evaluation.changes.truth import change_truth, score_changes
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import simulate


def _one(seed: int, args: argparse.Namespace) -> dict[str, object]:
    base = dataclasses.replace(load_scenario(args.scenario), steps=args.steps)
    changed = with_changes(
        base,
        np.random.default_rng(1000 + seed),
        moved=args.moved,
        removed=args.removed,
        added=args.added,
    )
    params = ChangeParams(level=args.level)
    row: dict[str, object] = {"seed": seed}
    for name, sc in (("unchanged", base), ("changed", changed)):
        log = simulate(sc, seed=seed, workers=1).log
        r = run(log, "ekf", fusion=True)
        m = r.metrics
        row[f"{name}_rmse_m"] = m["position_error_m"]["rmse"]
        row[f"{name}_nees_mean"] = m["nees"]["mean"]
        if r.result.anchor is None:
            row[f"{name}_anchor"] = False
            continue
        row[f"{name}_anchor"] = True
        rep = detect_changes(r.result, log, params)
        truth = change_truth(sc, log, params)
        row[f"{name}_counts"] = rep.counts()
        row[f"{name}_score"] = score_changes(rep, truth).as_dict()
        moves = []
        for c in rep.known:
            if c.known_id in truth.moved:
                dx, dy, dth, _ = truth.moved[c.known_id]
                moves.append(
                    {
                        "id": c.known_id,
                        "kind": c.kind.name.lower(),
                        "true_m": float(np.hypot(dx, dy)),
                        "true_rad": float(dth),
                        "status": c.status.value,
                        "observed": c.known_id in truth.observed,
                    }
                )
        row[f"{name}_moves"] = moves
        row[f"{name}_missing_or_removed"] = [
            {
                "id": c.known_id,
                "status": c.status.value,
                "scans_in_view": c.scans_in_view,
                "removed": c.known_id in truth.removed,
                "removed_in_view": c.known_id in truth.removed_in_view,
            }
            for c in rep.known
            if c.status.value == "missing" or c.known_id in truth.removed
        ]
    return row


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--scenario", default="loop600")
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--seeds", type=int, nargs=2, default=(0, 20))
    p.add_argument("--moved", type=float, default=0.15)
    p.add_argument("--removed", type=float, default=0.05)
    p.add_argument("--added", type=float, default=0.0)
    p.add_argument("--level", type=float, default=0.999)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    for seed in range(*args.seeds):
        row = _one(seed, args)
        with open(args.out, "a") as f:
            f.write(json.dumps(row) + "\n")
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
