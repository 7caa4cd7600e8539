"""Wall time of simulating loop600 (motion, 2,400 laser scans, feature extraction).

Prints one JSON object.  Target: ≤ 20 s on the 2-core project machine.

``wall_time_s`` is the best of ``--repeat`` runs of :func:`simulate` with ``workers``
extraction processes (the library's default unless ``--workers`` is given);
``cpu_time_s`` is the processor time of that run, workers included, which does not
depend on what else the machine is doing.  ``laser_s`` and ``extraction_s`` split the
serial cost of the same scans.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from mapfuse_core.perception.extraction import extract_features
from mapfuse_core.sim.laser import simulate_scan
from mapfuse_core.sim.scenario import load_scenario
from mapfuse_core.sim.simulate import extraction_workers, simulate


def _cpu_s() -> float:
    """Processor time of this process and its finished children (the pool's workers)."""
    t = os.times()
    return t.user + t.system + t.children_user + t.children_system


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="loop600")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--workers", type=int, default=None, help="default: the library's")
    args = ap.parse_args()
    scenario = load_scenario(args.scenario)
    workers = extraction_workers(args.workers, scenario.steps)
    runs = []
    for _ in range(args.repeat):
        c0, t0 = _cpu_s(), time.perf_counter()
        result = simulate(scenario, seed=args.seed, workers=workers)
        runs.append((time.perf_counter() - t0, _cpu_s() - c0))
    wall, cpu = min(runs)
    # Split the cost: ray casting alone, then extraction alone, on the same poses.
    rng = np.random.default_rng(args.seed)
    poses = result.log.true_poses
    assert poses is not None
    t0 = time.perf_counter()
    scans = [simulate_scan(scenario.world, p, scenario.laser, rng) for p in poses]
    t_laser = time.perf_counter() - t0
    t0 = time.perf_counter()
    for s in scans:
        extract_features(s, scenario.laser)
    t_extract = time.perf_counter() - t0
    print(
        json.dumps(
            {
                "benchmark": "simulate",
                "scenario": args.scenario,
                "seed": args.seed,
                "steps": result.log.n_steps,
                "features": result.log.n_features,
                "workers": workers,
                "wall_time_s": round(wall, 3),
                "cpu_time_s": round(cpu, 3),
                "laser_s": round(t_laser, 3),
                "extraction_s": round(t_extract, 3),
                "target_s": 20.0,
                "cpu_count": os.cpu_count(),
                "load_average_1min": (
                    round(os.getloadavg()[0], 2) if hasattr(os, "getloadavg") else None
                ),
                "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            }
        )
    )


if __name__ == "__main__":
    main()
