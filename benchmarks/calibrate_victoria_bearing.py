"""Victoria Park: the laser's bearing offset against the EKF's loop closures (prints JSON).

Not a speed benchmark: the study behind ``VictoriaParkOptions.bearing_offset_rad``
(see ``VICTORIA_PARK_CALIBRATION_NOTE``).  For each offset the whole run goes through
the EKF as ``mapfuse run victoria-park`` runs it (``run_backend``; without
fusion, which is the same on a log with no known map), and the rotations of
its loop closures (``EKFResult.loop_closures``) are summarised: a yaw error of the
laser turns every map the car builds on new ground the same way, so when the car comes
back the closures all rotate with one sign.  The offset is chosen where their mean is
zero, which uses no GPS.  The GPS error (best fit) is printed beside it for the record
only.  About 35 s per offset on the project machine.

``--data DIR`` is the real-data directory (``../shared/data`` by default).
"""

from __future__ import annotations

import argparse
import json
import math
import time
from typing import Any

import numpy as np

from mapfuse_core.datasets import VictoriaParkOptions, load_victoria_park
from mapfuse_graph.runner import run_backend

OFFSETS_RAD = (-0.0235, -0.020, -0.018, -0.017, -0.016, -0.012)


def _row(data: str, offset: float) -> dict[str, Any]:
    log = load_victoria_park(data, options=VictoriaParkOptions(bearing_offset_rad=offset))
    t0 = time.process_time()
    run = run_backend(log, "ekf", fusion=False)
    cpu = time.process_time() - t0
    assert run.ekf is not None
    res = run.ekf
    rot = np.degrees([lc.correction[2] for lc in res.loop_closures])
    gps = run.metrics["position_error_m"] or {}
    return {
        "bearing_offset_rad": offset,
        "bearing_offset_deg": round(math.degrees(offset), 3),
        "loop_closures": len(rot),
        "rotation_mean_deg": round(float(rot.mean()), 3) if rot.size else None,
        "rotation_median_deg": round(float(np.median(rot)), 3) if rot.size else None,
        "rotation_std_error_deg": (
            round(float(rot.std(ddof=1) / math.sqrt(rot.size)), 3) if rot.size > 1 else None
        ),
        "rotations_positive": int((rot > 0).sum()),
        "rotations_deg": [round(float(r), 3) for r in rot],
        "map_features": int(res.global_map.n_obs.size),
        "cpu_time_s": round(cpu, 1),
        "gps_median_m_for_the_record": round(gps.get("median", float("nan")), 3),
        "gps_rmse_m_for_the_record": round(gps.get("rmse", float("nan")), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data")
    ap.add_argument("--offsets", type=float, nargs="+", default=list(OFFSETS_RAD))
    args = ap.parse_args()
    rows = [_row(args.data, o) for o in args.offsets]
    print(json.dumps({"study": "victoria_park_bearing_offset", "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
