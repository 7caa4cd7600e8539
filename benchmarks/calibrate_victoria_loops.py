"""Victoria Park: the odometry's sideways slip and the laser's bearing offset against the
EKF's loop closures (prints JSON).

Not a speed benchmark: the study behind ``VICTORIA_PARK_ODOMETRY_NOISE`` and
``VictoriaParkOptions.bearing_offset_rad`` (``docs/results/victoria-park-calibration.md``).  For
each setting the whole run goes through the EKF as ``mapfuse run victoria-park`` runs it
(``mapfuse.runner.run``; without fusion, which is the same on a log with no known map), and the
rotations of its loop closures (``EKFDetails.loop_closures``) are summarised.  Anything
that makes every map the car builds on new ground turn the same way (a yaw error of the
laser, or a motion model that meets sideways motion only with turns) makes the closures
rotate with one sign when the car comes back; the setting is chosen where their mean is
zero, which uses no GPS.  The GPS error (best fit) is printed beside it as a check,
not as a criterion.  The docs page gives the time per setting.

``--data DIR`` is the real-data directory (``../shared/data`` by default); ``--slips``
(m/√m) and ``--offsets`` (rad) give the grid, every slip with every offset.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import time
from typing import Any

import numpy as np

from mapfuse.runner import run
from mapfuse_core.data.datasets import (
    VICTORIA_PARK_ODOMETRY_NOISE,
    VictoriaParkOptions,
    load_victoria_park,
)

SLIPS = (0.01, 0.02, 0.04, 0.08)
OFFSETS_RAD = (0.0,)


def _row(data: str, slip: float, offset: float) -> dict[str, Any]:
    noise = dataclasses.replace(VICTORIA_PARK_ODOMETRY_NOISE, sigma_slip_m_per_sqrt_m=slip)
    options = VictoriaParkOptions(odometry_noise=noise, bearing_offset_rad=offset)
    log = load_victoria_park(data, options=options)
    t0 = time.process_time()
    done = run(log, "ekf", fusion=False)
    cpu = time.process_time() - t0
    res = done.result
    rot = np.degrees([lc.correction[2] for lc in res.details.loop_closures])
    gps = done.metrics.position_error
    return {
        "slip_m_per_sqrt_m": slip,
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
        "map_features": int(res.map.n_obs.size),
        "cpu_time_s": round(cpu, 1),
        "gps_median_m_for_the_record": round(gps.median if gps else float("nan"), 3),
        "gps_rmse_m_for_the_record": round(gps.rmse if gps else float("nan"), 3),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default="../shared/data")
    ap.add_argument("--slips", type=float, nargs="+", default=list(SLIPS))
    ap.add_argument("--offsets", type=float, nargs="+", default=list(OFFSETS_RAD))
    args = ap.parse_args()
    rows = [_row(args.data, s, o) for s in args.slips for o in args.offsets]
    print(json.dumps({"study": "victoria_park_loop_closures", "runs": rows}, indent=2))


if __name__ == "__main__":
    main()
