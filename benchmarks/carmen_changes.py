"""Change detection on a real CARMEN log, with its floor plan as built and with known
changes made to the plan (``docs/results/carmen.md``).

The plan is built from the log's own scans along the reference trajectory, so every
wall in it stands.  Three EKF runs with fusion, each classified with the log's own
scanner (``mapfuse.carmen_input.carmen_change_params``):

* **as built**: every wall should be confirmed or unobserved; a moved or missing wall
  is a false alarm, and a wall the raw scans saw empty is a free-space false alarm;
* **phantoms**: ``--phantoms`` walls of ``--length`` m that do not exist, put across
  the reference path at the reference pose of evenly spaced steps (the robot drove
  through each of them, so none can stand): each should be reported as a change
  (missing, or moved onto a landmark the plan lacks), never confirmed;
* **removed**: every ``--remove-every``-th plan wall taken out of the plan: the walls
  still stand, so their landmarks should be reported new (the log's reference labels
  say which landmark is which wall).

One JSON object is printed.

    PYTHONPATH=. python benchmarks/carmen_changes.py ../shared/data/carmen/intel-corrected.log.gz
"""

from __future__ import annotations

import argparse
import json
import math
from typing import Any

import numpy as np

from mapfuse.carmen_input import carmen_change_params, load_carmen_input
from mapfuse.changes import detect_changes
from mapfuse.runner import run
from mapfuse_core.changes import ChangeParams, ChangeReport
from mapfuse_core.data.datasets.carmen import with_known_map
from mapfuse_core.measlog import KnownMapArrays, MeasurementLog


def _classify(log: MeasurementLog) -> ChangeReport:
    r = run(log, "ekf", fusion=True)
    if r.result.anchor is None:
        raise SystemExit(f"no map match on {log.scenario}: {r.result.matching}")
    return detect_changes(r.result, log, carmen_change_params(log, ChangeParams()))


def _subset(km: KnownMapArrays, keep: np.ndarray) -> KnownMapArrays:
    ext = None if km.extents is None else km.extents[keep]
    return KnownMapArrays(km.ids[keep], km.kinds[keep], km.params[keep], km.covs[keep], ext)


def _with_phantoms(log: MeasurementLog, n: int, length: float) -> tuple[MeasurementLog, list[int]]:
    km = log.known_map
    if log.true_poses is None or km.extents is None:
        raise SystemExit("phantom walls need a corrected log (reference poses) and wall extents")
    steps = np.linspace(0, log.n_steps - 1, n + 2)[1:-1].round().astype(int)
    first = int(km.ids.max()) + 1
    ids = np.arange(first, first + n, dtype=np.int64)
    params = np.array([[p[0], p[1], p[2] + math.pi / 2] for p in log.true_poses[steps]])
    # Each phantom has the σ of the plan's median wall.
    cov = np.median(km.covs, axis=0)
    out = KnownMapArrays(
        ids=np.concatenate([km.ids, ids]),
        kinds=np.concatenate([km.kinds, np.full(n, km.kinds[0], dtype=np.int8)]),
        params=np.vstack([km.params, params]),
        covs=np.concatenate([km.covs, np.repeat(cov[None], n, axis=0)]),
        extents=np.vstack([km.extents, np.tile([-0.5 * length, 0.5 * length], (n, 1))]),
    )
    return with_known_map(log, out), ids.tolist()


def _as_built(rep: ChangeReport) -> dict[str, Any]:
    return {
        "counts": rep.counts(),
        "walls": len(rep.known),
        "moved": [
            {
                "id": c.known_id,
                "displacement": np.round(c.displacement, 3).tolist(),
                "n_obs": c.n_obs,
            }
            for c in rep.known
            if c.status.value == "moved"
        ],
        "seen_empty": sum(1 for c in rep.known if c.scans_seen_empty >= 1),
        **{k: v for k, v in rep.as_dict().items() if k in ("verdict", "consistency")},
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("log", help="a corrected CARMEN log (.log or .log.gz)")
    p.add_argument("--phantoms", type=int, default=12)
    p.add_argument("--length", type=float, default=1.0, help="phantom wall length (m)")
    p.add_argument("--remove-every", type=int, default=10)
    args = p.parse_args()
    log = load_carmen_input(f"carmen:{args.log}")
    out: dict[str, Any] = {"log": log.scenario, "steps": log.n_steps}
    out["as_built"] = _as_built(_classify(log))

    ph_log, ph_ids = _with_phantoms(log, args.phantoms, args.length)
    rep = _classify(ph_log)
    rows = {c.known_id: c for c in rep.known}
    classes = [rows[i].status.value for i in ph_ids]
    out["phantoms"] = {
        "n": len(ph_ids),
        "length_m": args.length,
        "per_class": {s: classes.count(s) for s in sorted(set(classes))},
        "reported_changed": sum(s in ("moved", "missing") for s in classes),
        "scans_seen_empty": [rows[i].scans_seen_empty for i in ph_ids],
        "plan_walls_moved_or_missing": sum(
            c.status.value in ("moved", "missing") for c in rep.known if c.known_id not in ph_ids
        ),
    }

    km = log.known_map
    drop = np.arange(len(km)) % args.remove_every == args.remove_every - 1
    removed = km.ids[drop].tolist()
    rep = _classify(with_known_map(log, _subset(km, ~drop)))
    found = {n.true_id for n in rep.new} & set(removed)
    seen = set(int(t) for t in log.feat_true_id[np.isin(log.feat_true_id, removed)])
    out["removed_from_plan"] = {
        "n": len(removed),
        "observed": len(seen),
        "reported_new": len(found),
        "counts": rep.counts(),
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
