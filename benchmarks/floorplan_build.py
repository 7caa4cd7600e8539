"""Building the floor plan of each CARMEN log: CPU time and a digest of the plan
(prints JSON, one line per log).

The digest (SHA-256 of the walls' parameters, covariances and extents, and of every
observation's wall) tells whether a change to the builder changed a plan: a change
meant to be faster only must leave every digest as it was.

    PYTHONPATH=. python benchmarks/floorplan_build.py --repeat 3
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time

import numpy as np

from benchmarks.carmen_frontend import add_log_arguments, resolve_logs
from mapfuse_core.data.datasets import CarmenOptions, FloorPlan, build_floor_plan, load_carmen


def digest(plan: FloorPlan) -> str:
    """SHA-256 (first 16 hex digits) of everything the plan holds."""
    h = hashlib.sha256()
    w = plan.walls
    for a in (w.params, w.covs, w.extents, plan.obs_wall, plan.n_obs):
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_log_arguments(ap)
    ap.add_argument("--repeat", type=int, default=3, help="builds per log; the least CPU counts")
    args = ap.parse_args()
    for path in resolve_logs(args.data, args.logs):
        log = load_carmen(path, options=CarmenOptions(seed=args.seeds[0]))
        cpu = []
        for _ in range(args.repeat):
            c0 = time.process_time()
            plan = build_floor_plan(log)
            cpu.append(time.process_time() - c0)
        row = {
            "log": path.name.split("-corrected")[0],
            "walls": len(plan.walls),
            "digest": digest(plan),
            "cpu_s_min": min(cpu),
        }
        print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
