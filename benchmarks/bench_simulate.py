"""Wall time of simulating loop600 (motion, 2,400 laser scans, feature extraction).

Prints one JSON object.  Target (issue 2): ≤ 20 s on the 2-core project machine.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np

from mapfuse_core.extraction import extract_features
from mapfuse_core.laser import simulate_scan
from mapfuse_core.scenario import load_scenario
from mapfuse_core.simulate import simulate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--scenario", default="loop600")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeat", type=int, default=1)
    args = ap.parse_args()
    scenario = load_scenario(args.scenario)
    totals = []
    for _ in range(args.repeat):
        t0 = time.perf_counter()
        result = simulate(scenario, seed=args.seed)
        totals.append(time.perf_counter() - t0)
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
                "wall_time_s": round(min(totals), 3),
                "laser_s": round(t_laser, 3),
                "extraction_s": round(t_extract, 3),
                "target_s": 20.0,
                "machine": f"{platform.machine()} {platform.processor() or ''}".strip(),
            }
        )
    )


if __name__ == "__main__":
    main()
